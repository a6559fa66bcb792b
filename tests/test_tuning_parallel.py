"""Several workers on one study at once: journal file, PostgreSQL (when a server is given), --jobs.

The PostgreSQL test reads the server's URL from ``SB3_GRAPH_TEST_POSTGRES_URL`` (``scripts/postgres.sh``
starts a throwaway server on loopback and prints it) and is skipped when the variable is unset.
"""

import os
import subprocess
import sys
import uuid
from collections import Counter

import optuna
import pytest
import yaml
from optuna.trial import TrialState

from sb3_graph.tuning.storage import make_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)
TOY = "GraphMaxNeighbour-v0"
ENTRY = {
    "n_timesteps": 120,
    "policy": "GraphPolicy",
    "learning_starts": 40,
    "batch_size": 16,
    "buffer_size": 500,
    "train_freq": 4,
    "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])",
}
TRIALS_PER_WORKER = 2


def command(config, storage, study, *extra):
    return [sys.executable, "-m", "sb3_graph.cli", "tune", "--config", str(config), "--env", TOY,
            "--study-name", study, "--storage", storage, "--tune-algo", "--eval-episodes", "1",
            "--n-trials", str(TRIALS_PER_WORKER), *extra]  # fmt: skip


def run_at_once(commands):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "SB3_GRAPH_NO_PROGRESS": "1"}
    processes = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
                 for c in commands]  # fmt: skip
    outputs = [p.communicate(timeout=300)[0] for p in processes]
    for process, output in zip(processes, outputs):
        assert process.returncode == 0, output


def check_one_study(storage, study_name, workers):
    study = optuna.load_study(study_name=study_name, storage=make_storage(storage))
    trials = study.get_trials()
    total = workers * TRIALS_PER_WORKER
    assert sorted(t.number for t in trials) == list(range(total))  # none lost, none duplicated
    assert [t.state for t in trials] == [TrialState.COMPLETE] * total
    per_worker = Counter(t.user_attrs["worker"] for t in trials)
    assert len(per_worker) == workers and set(per_worker.values()) == {TRIALS_PER_WORKER}
    assert len({t.user_attrs["seed"] for t in trials}) == total  # every trial trains with its own seed


@pytest.fixture
def config(tmp_path):
    path = tmp_path / "toy.yml"
    path.write_text(yaml.safe_dump({TOY: ENTRY}))
    return path


def test_two_workers_share_a_journal_file(config, tmp_path):
    storage = f"journal://{tmp_path}/shared/study.log"
    run_at_once([command(config, storage, "journal"), command(config, storage, "journal")])
    check_one_study(storage, "journal", workers=2)


def test_jobs_start_worker_processes_on_sqlite(config, tmp_path):
    storage = f"sqlite:///{tmp_path}/study.db"
    cmd = command(config, storage, "jobs", "--jobs", "2")
    cmd[cmd.index("--n-trials") + 1] = str(2 * TRIALS_PER_WORKER)  # shared between the two workers
    run_at_once([cmd])
    check_one_study(storage, "jobs", workers=2)


@pytest.mark.skipif(
    not os.environ.get("SB3_GRAPH_TEST_POSTGRES_URL"),
    reason="SB3_GRAPH_TEST_POSTGRES_URL is unset (start a server with scripts/postgres.sh)",
)
def test_two_workers_share_a_postgresql_study(config):
    storage = os.environ["SB3_GRAPH_TEST_POSTGRES_URL"]
    study = f"parallel-{uuid.uuid4().hex[:8]}"  # the server may outlive one test run
    run_at_once([command(config, storage, study), command(config, storage, study)])
    check_one_study(storage, study, workers=2)
