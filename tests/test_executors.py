"""Where the harness's runs execute (:mod:`sb3_graph.common.executors`): local processes, a Dask cluster, one's own."""

from __future__ import annotations

import json
import operator
import os
import sys

import pandas as pd
import pytest

from sb3_graph.cli import main
from sb3_graph.common.executors import ExecutorError, JobExecutor, LocalExecutor, check_executor, make_executor

TINY = ["--planner", "pr", "--planner", "fifo", "--scenarios", "2", "--duration", "10", "--seed", "1"]
TINY += ["--no-progress"]


def _add_with_pid(item, shared):
    return item + shared[0], os.getpid(), id(shared)


def test_local_pool_runs_every_item_and_sends_the_shared_object_once_per_worker():
    with LocalExecutor(workers=2) as executor:
        results = dict(executor.map_unordered(_add_with_pid, list(range(8)), [10] * 1000))
    assert sorted(results) == list(range(8)) and [results[k][0] for k in range(8)] == list(range(10, 18))
    # Every call in one worker process sees the same object: it was unpickled once, not once per item.
    for pid in {pid for _, pid, _ in results.values()}:
        assert len({shared for _, p, shared in results.values() if p == pid}) == 1


def test_a_failed_call_raises_its_error():
    with LocalExecutor(workers=1) as executor, pytest.raises(TypeError):
        list(executor.map_unordered(operator.add, [1, "x"], 1))


class _Recording(JobExecutor):
    """An executor of one's own: runs in this process, remembers what it ran."""

    name = "recording"

    def __init__(self):
        super().__init__(workers=1)
        self.items = 0

    def map_unordered(self, fn, items, shared):
        for k in reversed(range(len(items))):  # out of order, as a cluster would finish
            self.items += 1
            yield k, fn(items[k], shared)


def test_an_executor_of_ones_own_gives_the_local_numbers(tmp_path):
    from envs.evaluation.harness import evaluate, generate_scenarios

    scenarios = generate_scenarios(tmp_path / "s", 2, 10.0, 1, "4way")
    planners = [("pr", "PR"), ("fifo", "FIFO")]
    args = (planners, scenarios, "CoopIntersection4Way-v0", 10.0)
    stats: dict = {}
    local, _ = evaluate(*args, seed=1, progress=False, stats=stats)
    mine = _Recording()
    other, _ = evaluate(*args, seed=1, progress=False, executor=mine)
    assert mine.items == 4
    pd.testing.assert_frame_equal(local.drop(columns="wall_s"), other.drop(columns="wall_s"))
    assert stats["runs"] == 4 and stats["runs_per_s"] > 0 and stats["executor"] == "local, in this process"


@pytest.mark.parametrize("command", ["evaluate", "sweep", "ind"])
def test_unknown_executor_is_a_one_line_error(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--executor", "spark"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--executor" in err and "'spark'" in err and "local" in err and "dask" in err
    assert "Traceback" not in err


def test_scheduler_address_needs_a_cluster_executor(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["evaluate", *TINY, "--scheduler-address", "tcp://127.0.0.1:8786", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--scheduler-address" in err and "--executor dask" in err
    assert not out.exists()


def test_missing_cluster_package_names_the_pip_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails, as where it is not installed
    assert main(["evaluate", *TINY, "--executor", "ray", "--out", str(tmp_path / "r")]) == 2
    assert "pip install 'sb3-graph[ray]'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--executor"):
        check_executor("spark")
    with pytest.raises(ExecutorError, match="--scheduler-address"):
        make_executor("local", 2, "tcp://127.0.0.1:8786")


def _same_report(one, two):
    for name in ("summary.json", "paired.csv"):
        assert (one / name).read_text() == (two / name).read_text(), name
    metrics = [pd.read_csv(folder / "metrics.csv").drop(columns="wall_s") for folder in (one, two)]
    pd.testing.assert_frame_equal(*metrics)


def test_dask_cluster_gives_the_same_summary_as_local_processes(tmp_path):
    distributed = pytest.importorskip("distributed")  # in the test extra: runs in CI
    assert main(["evaluate", *TINY, "--jobs", "1", "--out", str(tmp_path / "local")]) == 0
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        argv = ["evaluate", *TINY, "--executor", "dask", "--scheduler-address", cluster.scheduler_address]
        assert main([*argv, "--out", str(tmp_path / "dask")]) == 0
    _same_report(tmp_path / "local", tmp_path / "dask")
    run = json.loads((tmp_path / "dask" / "run.json").read_text())
    assert run["runs"] == 4 and run["runs_per_s"] > 0
    assert run["executor"].startswith("dask, 2 workers (the cluster at tcp://")
    assert json.loads((tmp_path / "local" / "run.json").read_text())["executor"] == "local, in this process"


def test_ray_gives_the_same_summary_as_local_processes(tmp_path):
    pytest.importorskip("ray")  # not in the test extra (large): runs where Ray is installed
    assert main(["evaluate", *TINY, "--jobs", "1", "--out", str(tmp_path / "local")]) == 0
    assert main(["evaluate", *TINY, "--executor", "ray", "--jobs", "2", "--out", str(tmp_path / "ray")]) == 0
    _same_report(tmp_path / "local", tmp_path / "ray")
    assert json.loads((tmp_path / "ray" / "run.json").read_text())["executor"] == "ray, 2 CPUs (a local cluster)"


def test_progress_bar_shows_runs_per_second_even_when_slow(monkeypatch):
    from envs.evaluation.harness import _progress

    monkeypatch.delenv("SB3_GRAPH_NO_PROGRESS", raising=False)
    bar = _progress(20, True)
    bar.update(1)
    meter = {**bar.format_dict, "elapsed": 10.0, "rate": None}  # one run in 10 s
    bar.close()
    text = bar.format_meter(**meter)
    assert "0.10run/s" in text and "s/run" not in text


def test_unreachable_dask_scheduler_is_a_clear_error():
    pytest.importorskip("distributed")
    from sb3_graph.common.executors import DaskExecutor

    # Port 1 on the loopback: nothing listens there; the client gives up after the timeout.
    with pytest.raises(ExecutorError, match="--scheduler-address: cannot reach the Dask scheduler"):
        DaskExecutor(address="tcp://127.0.0.1:1", connect_timeout=1)
