"""The planners in both plants: the side-by-side table, the paired differences per plant and whether each ranking
holds (``envs.evaluation.cross_plant``), and ``evaluate --plant builtin --plant sumo``."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from envs.evaluation.cross_plant import holding_counts, rankings, side_by_side, verdict, write_cross_plant
from sb3_graph.cli import main


@pytest.mark.parametrize(
    "lows, highs, expected",
    [
        ((0.1, 0.2), (0.3, 0.4), "holds"),
        ((-0.3, -0.4), (-0.1, -0.2), "holds"),
        ((0.1, -0.4), (0.3, -0.2), "reversed"),
        ((0.1, -0.1), (0.3, 0.2), "only in ours"),
        ((-0.1, -0.4), (0.3, -0.2), "only in SUMO"),
        ((-0.1, -0.1), (0.3, 0.2), "no ranking"),
        ((0.0, 0.1), (0.3, 0.2), "only in SUMO"),  # an interval that touches zero does not exclude it
    ],
)
def test_verdict(lows, highs, expected):
    assert verdict(lows, highs, ["builtin", "sumo"]) == expected


def _runs(flow_b: np.ndarray, delay_b: np.ndarray, rng: np.random.Generator) -> pd.DataFrame:
    """Planner A and B on 12 scenarios; B's flow and delay are A's plus the given offsets (plus noise)."""
    n = 12
    flow_a, delay_a = rng.uniform(0.3, 0.5, n), rng.uniform(5, 10, n)
    stops = rng.uniform(0.2, 0.4, n)
    rows = []
    for planner, flow, delay in (("A", flow_a, delay_a), ("B", flow_a + flow_b, delay_a + delay_b)):
        for k in range(n):
            rows.append({
                "planner": planner, "scenario": f"s{k}", "flow_rate": flow[k], "delay_mean": delay[k],
                "stop_ratio_all": stops[k], "vehicles_all": 50, "stopped_all": 50 * stops[k], "collided": 0,
                "vehicles": 50, "stuck": False, "failed": False,
            })  # fmt: skip
    return pd.DataFrame(rows)


def test_rankings_hold_reverse_or_vanish_across_plants():
    """B gains flow in both plants (holds), its delay falls in one and rises in the other (reversed), its stops
    are A's (no ranking); a failed run is left out of the pairs."""
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 0.005, 12)
    ours = _runs(0.1 + noise, -2.0 + noise, np.random.default_rng(1))
    sumo = _runs(0.05 + noise, 1.5 + noise, np.random.default_rng(2))
    sumo.loc[(sumo["planner"] == "B") & (sumo["scenario"] == "s0"), ["failed", "flow_rate"]] = [True, np.nan]
    table = rankings({"builtin": ours, "sumo": sumo}, ["A", "B"]).set_index("metric")
    assert table.loc["flow_rate", "verdict"] == "holds"
    assert table.loc["delay_mean", "verdict"] == "reversed"
    assert table.loc["stop_ratio_all", "verdict"] == "no ranking"
    assert table.loc["flow_rate", "builtin_pairs"] == 12 and table.loc["flow_rate", "sumo_pairs"] == 11
    assert table.loc["flow_rate", "builtin_mean"] == pytest.approx(0.1 + noise.mean())
    assert holding_counts(table.reset_index(), "builtin") == {"ranked": 2, "holds": 1, "reversed": 1}
    side = side_by_side({"builtin": ours, "sumo": sumo}, ["A", "B"]).set_index(["planner", "plant"])
    assert side.loc[("B", "sumo"), "runs"] == 11 and side.loc[("B", "sumo"), "failed"] == 1


def test_write_cross_plant_writes_both_tables(tmp_path):
    ours = _runs(np.full(12, 0.1), np.full(12, -2.0), np.random.default_rng(1))
    line = write_cross_plant(tmp_path, {"builtin": ours, "sumo": ours}, ["A", "B"])
    assert line.startswith("2 of the 2 rankings in ours")
    text = (tmp_path / "plants.md").read_text()
    assert "| B − A | +0.100 [+0.100, +0.100] | +0.100 [+0.100, +0.100] | holds |" in text
    assert len(pd.read_csv(tmp_path / "plants.csv")) == 3


def test_sweep_runs_one_plant(capsys):
    assert main(["sweep", "--plant", "builtin", "--plant", "sumo", "--planner", "pr"]) == 2
    assert "--plant: this command runs one plant" in capsys.readouterr().err


def test_evaluate_in_both_plants(tmp_path):
    """Two planners on the same scenarios in our plant and in SUMO, both at SUMO's 20 Hz: a whole report per
    plant, the same scenario files in each, and without humans the same figures in both (the plants' parity)."""
    pytest.importorskip("libsumo")
    out = tmp_path / "cross"
    argv = ["evaluate", "--plant", "builtin", "--plant", "sumo", "--planner", "pr", "--planner", "glide+shield"]
    argv += ["--scenarios", "2", "--duration", "20", "--jobs", "1", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    for plant in ("builtin", "sumo"):
        info = json.loads((out / plant / "run.json").read_text())
        assert info["replay"]["env_kwargs"]["config"] == {"plant": plant, "simulation_frequency": 20}
        assert (out / plant / "report.md").is_file()
    scenarios = [
        sorted(p.read_text() for p in (out / plant / "scenarios").glob("*.json")) for plant in ("builtin", "sumo")
    ]
    assert len(scenarios[0]) == 2 and scenarios[0] == scenarios[1]
    ours, sumo = (
        pd.read_csv(out / plant / "metrics.csv").sort_values(["planner", "run"]) for plant in ("builtin", "sumo")
    )
    for column in ("flow_rate", "delay_mean", "stop_ratio_all", "collided"):
        assert np.allclose(ours[column], sumo[column], atol=1e-6), column
    table = pd.read_csv(out / "plants.csv")
    assert set(table["verdict"]) <= {"holds", "no ranking"}  # identical figures: nothing reverses
    assert "Glide+shield − PR" in (out / "plants.md").read_text()
