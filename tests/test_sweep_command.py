"""``sb3-graph sweep`` end to end on a tiny run, its capacity rule, and its refusals."""

from __future__ import annotations

import json

import matplotlib.image
import pandas as pd
import pytest

from envs.evaluation.report import REPORT_FILES
from envs.evaluation.sweep import capacities, capacity_text
from sb3_graph.cli import main

TINY = ["--scenarios", "1", "--duration", "10", "--seed", "2", "--jobs", "1", "--no-progress"]


def test_tiny_sweep_writes_both_files_with_the_schema(tmp_path):
    out = tmp_path / "sweep"
    args = ["sweep", "--planner", "pr", "--planner", "fifo", "--demand", "0.3", "0.1", "--out", str(out)]
    assert main([*args, *TINY]) == 0
    table = pd.read_csv(out / "sweep.csv")
    assert list(table.columns) == [
        "planner", "demand", "flow_rate", "delay_mean_s", "stop_ratio", "collision_rate", "speed_limit_violations",
        "slow_ratio", "hard_brakes_per_vehicle", "energy_kj_per_vehicle",
    ]  # fmt: skip
    assert list(zip(table["planner"], table["demand"])) == [("PR", 0.1), ("FIFO", 0.1), ("PR", 0.3), ("FIFO", 0.3)]
    assert table[["flow_rate", "delay_mean_s", "stop_ratio", "collision_rate"]].notna().all().all()
    assert (table["speed_limit_violations"] >= 0).all()
    image = matplotlib.image.imread(out / "sweep.png")
    assert image.shape[0] > 100 and image.shape[1] > 300
    assert "## Capacity" in (out / "sweep.md").read_text()
    for level in ("demand_0.1", "demand_0.3"):  # an evaluate-style report per level
        for name in REPORT_FILES:
            assert (out / level / name).is_file(), (level, name)
        scenario = json.loads(next((out / level / "scenarios").iterdir()).read_text())
        assert scenario["meta"]["demand"] == float(level.split("_")[1])
        summary = json.loads((out / level / "summary.json").read_text())
        assert summary["PR"]["vehicles_scheduled"] == summary["FIFO"]["vehicles_scheduled"]
        row = table[(table["planner"] == "PR") & (table["demand"] == float(level.split("_")[1]))].iloc[0]
        assert row["flow_rate"] == pytest.approx(summary["PR"]["flow_rate"]["mean"])
        assert row["speed_limit_violations"] == summary["PR"]["speed_limit_violations"]
    # the higher demand offers more traffic
    low = json.loads((out / "demand_0.1" / "summary.json").read_text())["PR"]
    high = json.loads((out / "demand_0.3" / "summary.json").read_text())["PR"]
    assert high["vehicles_scheduled"] > low["vehicles_scheduled"]


@pytest.mark.parametrize(
    "demand, message",
    [(["0"], "[0.001, 1)"), (["1.5"], "[0.001, 1)"), (["1e-300"], "[0.001, 1)"), (["0.1", "0.1"], "twice")],
)
def test_bad_demand_is_a_one_line_error(tmp_path, capsys, demand, message):
    out = tmp_path / "sweep"
    assert main(["sweep", "--planner", "pr", "--demand", *demand, "--out", str(out), *TINY]) == 2
    err = capsys.readouterr().err.strip()
    assert "--demand" in err and message in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_existing_out_is_refused(tmp_path, capsys):
    out = tmp_path / "sweep"
    out.mkdir()
    assert main(["sweep", "--planner", "pr", "--demand", "0.1", "--out", str(out), *TINY]) == 2
    assert "exists" in capsys.readouterr().err and not any(out.iterdir())


def test_capacity_is_the_last_level_before_flow_falls_short_of_the_offered_flow():
    table = pd.DataFrame(
        {
            "planner": ["A"] * 4 + ["B"] * 4 + ["C"] * 4,
            "demand": [0.1, 0.2, 0.3, 0.4] * 3,
            "offered_flow": [0.3, 0.6, 0.9, 1.2] * 3,
            "flow_rate": [0.3, 0.58, 0.6, 1.1] + [0.29, 0.6, 0.9, 1.15] + [0.2, 0.6, 0.9, 1.2],
        }
    )
    # A serves 0.1 and 0.2 (0.58 >= 0.9 * 0.6), not 0.3 (and 0.4 after a shortfall does not count);
    # B serves every level; C falls short at the lowest one
    assert capacities(table) == {"A": 0.2, "B": 0.4, "C": None}
    assert [capacity_text(c, 0.4) for c in (0.2, 0.4, None)] == ["0.2", ">= 0.4", "below the lowest level"]
