"""``sb3-graph reward-check``: rank correlations of rewards with the task metrics, from evaluate reports."""

from __future__ import annotations

import pandas as pd
import pytest

from envs.evaluation.harness import preset_returns
from envs.simulation.rewards import PAPER_REWARD_WEIGHTS, REWARD_PRESETS, TASK_REWARD_WEIGHTS
from sb3_graph.cli import main


def _report(tmp_path, rows) -> str:
    folder = tmp_path / "report"
    folder.mkdir()
    columns = ["planner", "flow_rate", "delay_mean", "stop_ratio_all", "collision_rate", "return_task", "return_paper"]
    pd.DataFrame(rows, columns=columns).to_csv(folder / "metrics.csv", index=False)
    return str(folder)


def test_the_task_reward_ranking_like_flow_passes_and_the_reversed_one_fails(tmp_path, capsys):
    # Three planners, two runs each: the task return follows flow, the paper's return is reversed.
    rows = [
        ("A", 0.7, 5.0, 0.4, 0.0, -30.0, 1.0),
        ("A", 0.8, 4.0, 0.4, 0.0, -20.0, 2.0),
        ("B", 0.5, 10.0, 0.2, 0.0, -80.0, 5.0),
        ("B", 0.5, 12.0, 0.2, 0.0, -90.0, 6.0),
        ("C", 0.2, 30.0, 0.9, 0.0, -300.0, 9.0),
        ("C", 0.3, 28.0, 0.9, 0.0, -280.0, 8.0),
    ]
    report = _report(tmp_path, rows)
    assert main(["reward-check", report, "--min-rho", "0.8"]) == 0
    out = capsys.readouterr().out
    assert "task" in out and "+1.00" in out and "-1.00" in out
    assert main(["reward-check", report, "--reward", "paper", "--min-rho", "0.8"]) == 1
    assert "does NOT rank like the task" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, message",
    [
        (["--min-rho", "2"], "--min-rho"),
        (["--reward", "speed"], "--reward"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, args, message):
    rows = [
        ("A", 0.7, 5.0, 0.4, 0.0, -30.0, 1.0),
        ("B", 0.5, 9.0, 0.2, 0.0, -80.0, 5.0),
        ("C", 0.2, 30.0, 0.9, 0.0, -1, 9),
    ]
    assert main(["reward-check", _report(tmp_path, rows), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_report_without_returns_is_refused(tmp_path, capsys):
    folder = tmp_path / "old"
    folder.mkdir()
    pd.DataFrame({"planner": ["A"], "flow_rate": [0.5]}).to_csv(folder / "metrics.csv", index=False)
    assert main(["reward-check", str(folder)]) == 2
    assert "lacks the columns" in capsys.readouterr().err


def test_preset_returns_weigh_the_summed_terms_with_each_preset():
    terms = {"velocity": 10.0, "idle": -2.0, "throughput": 5.0, "delay": -30.0, "stop": -3.0, "collision": -1.0}
    returns = preset_returns(terms)
    assert set(returns) == {f"return_{name}" for name in REWARD_PRESETS}
    paper = sum(PAPER_REWARD_WEIGHTS[k] * terms.get(k, 0.0) for k in PAPER_REWARD_WEIGHTS)
    task = sum(TASK_REWARD_WEIGHTS[k] * terms.get(k, 0.0) for k in TASK_REWARD_WEIGHTS)
    assert returns["return_paper"] == pytest.approx(paper) and returns["return_task"] == pytest.approx(task)
