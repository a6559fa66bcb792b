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


def test_tiny_sweep_writes_both_files_with_the_schema(tmp_path, capsys):
    out = tmp_path / "sweep"
    args = ["sweep", "--planner", "rules=pr", "--planner", "fifo", "--demand", "0.3", "0.1", "--out", str(out)]
    assert main([*args, *TINY]) == 0
    last = capsys.readouterr().out.splitlines()[-4:]  # who leads per level, then the folder
    assert last[0].startswith("Who leads at each demand level")
    assert [line.split(":")[0] for line in last[1:3]] == ["  demand 0.1", "  demand 0.3"]
    assert all("flow: " in line and "delay: " in line and "stops: " in line for line in last[1:3])
    assert last[3].startswith(f"sweep written to {out}")
    table = pd.read_csv(out / "sweep.csv")
    assert list(table.columns) == [
        "planner", "demand", "flow_rate", "delay_mean_s", "stop_ratio", "collision_rate", "speed_limit_violations",
        "slow_ratio", "hard_brakes_per_vehicle", "energy_kj_per_vehicle", "failed_runs",
    ]  # fmt: skip
    assert (table["failed_runs"] == 0).all()
    # the label is the report name
    assert list(zip(table["planner"], table["demand"])) == [
        ("rules", 0.1), ("FIFO", 0.1), ("rules", 0.3), ("FIFO", 0.3)
    ]  # fmt: skip
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
        assert summary["rules"]["vehicles_scheduled"] == summary["FIFO"]["vehicles_scheduled"]
        row = table[(table["planner"] == "rules") & (table["demand"] == float(level.split("_")[1]))].iloc[0]
        assert row["flow_rate"] == pytest.approx(summary["rules"]["flow_rate"]["mean"])
        assert row["speed_limit_violations"] == summary["rules"]["speed_limit_violations"]
        assert (out / level / "report.md").read_text().splitlines()[2] == "## Verdict"
    # the higher demand offers more traffic
    low = json.loads((out / "demand_0.1" / "summary.json").read_text())["rules"]
    high = json.loads((out / "demand_0.3" / "summary.json").read_text())["rules"]
    assert high["vehicles_scheduled"] > low["vehicles_scheduled"]


RAISER = """
import numpy as np
from envs.planners.base import Planner

class Raiser(Planner):
    def __init__(self, name="Raiser"):
        super().__init__(name)
        self.steps = 0

    def reset(self, seed=None):
        self.steps = 0

    def act(self, scene):
        self.steps += 1
        if self.steps > 5:  # 1 s into every run
            raise RuntimeError("boom")
        return np.full(scene.num_vehicles, scene.a_max)
"""


@pytest.mark.parametrize("axis", [["--demand", "0.1", "0.2"], ["--human-share", "0", "1"]])
def test_a_planner_failing_every_run_is_reported_and_the_others_kept(tmp_path, capsys, axis):
    (tmp_path / "raiser.py").write_text(RAISER)
    out = tmp_path / "sweep"
    args = ["sweep", "--planner", f"{tmp_path / 'raiser.py'}:Raiser", "--planner", "fullthrottle+shield"]
    assert main([*args, *axis, "--out", str(out), *TINY]) == 1
    printed = capsys.readouterr().out
    assert "planner error: Raiser, scenario scenario_000.json, step 5 (t = 1.0 s): raised RuntimeError: boom" in printed
    assert "2 runs failed on a planner error" in printed
    table = pd.read_csv(out / "sweep.csv").set_index("planner")
    assert (table.loc["Raiser", "failed_runs"] == 1).all() and table.loc["Raiser", "flow_rate"].isna().all()
    kept = table.loc["FullThrottle+shield"]
    assert (kept["failed_runs"] == 0).all() and kept["flow_rate"].notna().all()
    text = (out / "sweep.md").read_text()
    assert "## Failed runs" in text and "- Raiser, " in text and "(every run)" in text
    if axis[0] == "--demand":
        assert "| Raiser | unknown (every run failed at a level) | n/a |" in text


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
