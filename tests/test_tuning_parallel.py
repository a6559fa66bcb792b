"""Several workers on one study at once: journal file, PostgreSQL (when a server is given), --jobs.

The PostgreSQL test reads the server's URL from ``SB3_GRAPH_TEST_POSTGRES_URL`` (``scripts/postgres.sh``
starts a throwaway server on loopback and prints it) and is skipped when the variable is unset.
"""

import os
import signal
import socket
import subprocess
import sys
import time
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


def _finished(trial):
    return trial.state.is_finished()


def _snapshot(trial):
    return trial.number, trial.state, trial.params, trial.values, trial.intermediate_values, trial.user_attrs


def test_killing_one_worker_keeps_every_finished_trial_on_resume(config, tmp_path):
    """Two workers on a journal file; one is SIGKILLed mid-trial. Its finished trials stay as they
    were, its running trial is failed by the heartbeat when the study resumes, and the study goes on."""
    storage = f"journal://{tmp_path}/kill/study.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "SB3_GRAPH_NO_PROGRESS": "1"}
    fast = ["--heartbeat", "1", "--pruner", "successive-halving", "--reduction-factor", "2"]
    victim_cmd = command(config, storage, "kill", *fast)
    victim_cmd[victim_cmd.index("--n-trials") + 1] = "20"  # killed long before it gets through them
    victim = subprocess.Popen(victim_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    survivor = subprocess.Popen(command(config, storage, "kill", *fast), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)  # fmt: skip
    victim_id = f"{socket.gethostname()}:{victim.pid}"
    deadline = time.monotonic() + 240
    try:
        while True:  # wait until the victim has finished a trial and is inside the next one
            assert time.monotonic() < deadline and victim.poll() is None, "the victim never got mid-trial"
            time.sleep(0.1)
            if not os.path.exists(f"{tmp_path}/kill/study.log"):
                continue
            try:
                trials = optuna.load_study(study_name="kill", storage=make_storage(storage)).get_trials()
            except KeyError:  # the study is not created yet
                continue
            mine = [t for t in trials if t.user_attrs.get("worker") == victim_id]
            running = [t.number for t in mine if t.state == TrialState.RUNNING]
            if any(map(_finished, mine)) and running:
                victim.send_signal(signal.SIGKILL)
                break
    finally:
        victim.kill()
        victim.wait()
    output = survivor.communicate(timeout=300)[0]
    assert survivor.returncode == 0, output

    study = optuna.load_study(study_name="kill", storage=make_storage(storage))
    # the victim's trial is left running by the kill (or already failed by the survivor's heartbeat check)
    assert study.trials[running[0]].state in (TrialState.RUNNING, TrialState.FAIL)
    before = {t.number: _snapshot(t) for t in study.get_trials() if _finished(t) and t.number != running[0]}
    assert any(snapshot[-1]["worker"] == victim_id for snapshot in before.values())
    time.sleep(2.5)  # two heartbeat intervals: the killed trial is stale
    resume = command(config, storage, "kill", *fast)
    resume[resume.index("--n-trials") + 1] = "1"
    run_at_once([resume])

    after = optuna.load_study(study_name="kill", storage=make_storage(storage)).get_trials()
    assert sorted(t.number for t in after) == list(range(len(after)))  # none lost, none duplicated
    for number, snapshot in before.items():
        assert _snapshot(after[number]) == snapshot  # every finished trial kept as it was
    assert after[running[0]].state == TrialState.FAIL  # failed by the heartbeat, not left running
    assert after[-1].state.is_finished() and after[-1].number not in before
    assert not [t for t in after if t.state == TrialState.RUNNING]
