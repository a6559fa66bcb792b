"""The scripts of ``examples/`` (the site's Examples page shows them) run as their docstrings say, shortened.

``examples/drive_a_planner.py`` is run by ``tests/test_record.py``; the others here.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sb3_graph.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def run_example(name: str, *args: str, cwd: Path = ROOT) -> str:
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / name), *args], capture_output=True, text=True, env=ENV, cwd=cwd,
        timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_gymnasium_graph_env_trains_ppo_on_a_gymnasium_graph_space():
    out = run_example("gymnasium_graph_env.py", "--steps", "128")
    assert "random policy: mean error per vehicle" in out and "PPO after 128 steps" in out


def test_aim_fast_runs_behind_the_shield_in_evaluate(tmp_path, capsys):
    # The docstring's command, shortened to one scenario of 20 s.
    code = main(["evaluate", "--planner", str(ROOT / "examples" / "aim_fast.py") + ":AIMFast+shield",
                 "--planner", "aim", "--scenarios", "1", "--duration", "20", "--jobs", "1", "--trust-planner-files",
                 "--no-progress", "--out", str(tmp_path / "report")])  # fmt: skip
    assert code == 0
    assert "AIMFast+shield" in (tmp_path / "report" / "metrics.csv").read_text()


@pytest.mark.slow
def test_learning_curve_scores_the_checkpoints_of_a_run(tmp_path):
    # A tiny run with two checkpoints, then the example on one short scenario.
    run = tmp_path / "run"
    tiny = ["--hyperparams", "learning_starts:64", "batch_size:16", "buffer_size:1000"]
    config = json.dumps({"config": {"duration": 8.0}})
    assert main(["train", "--config", str(ROOT / "zoo_configs" / "td3.yml"), "--env", "CoopIntersection4Way-v0",
                 "--out", str(run), "--n-timesteps", "200", "--eval-freq", "100", "--eval-episodes", "1",
                 "--checkpoint-freq", "100", "--no-progress", *tiny, "--env-kwargs", config]) == 0  # fmt: skip
    out = run_example("learning_curve.py", str(run), "--scenarios", "1", "--duration", "10", cwd=tmp_path)
    assert "| step |" in out or "step" in out
    assert (run / "learning_curve.csv").is_file()
