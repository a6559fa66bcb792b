"""scripts/paired.py joins reports that ran the same scenarios, and refuses others."""

import importlib.util
from pathlib import Path

import pandas as pd
import pytest

SCRIPT = Path(__file__).parents[1] / "scripts" / "paired.py"
spec = importlib.util.spec_from_file_location("paired", SCRIPT)
paired = importlib.util.module_from_spec(spec)
spec.loader.exec_module(paired)


def report(folder: Path, planner: str, flows: list[float], scenario_text: str = "{}") -> Path:
    (folder / "scenarios").mkdir(parents=True)
    names = [f"scenario_{i:03d}.json" for i in range(len(flows))]
    for name in names:
        (folder / "scenarios" / name).write_text(scenario_text)
    rows = {"planner": planner, "run": range(len(flows)), "scenario": names, "flow_rate": flows}
    rows.update({"delay_mean": [1.0] * len(flows), "stop_ratio_all": [0.5] * len(flows)})
    pd.DataFrame(rows).to_csv(folder / "metrics.csv", index=False)
    return folder


def test_differences_across_reports_against_the_chosen_baseline(tmp_path, capsys):
    a = report(tmp_path / "a", "A", [0.5, 0.6, 0.7])
    b = report(tmp_path / "b", "B", [0.4, 0.4, 0.4])
    assert paired.main([str(a), str(b), "--baseline", "B"]) == 0
    out = capsys.readouterr().out
    flow = [line for line in out.splitlines() if "flow_rate" in line][0].split()
    assert flow[:2] == ["A", "B"] and float(flow[4]) == pytest.approx(0.2)


def test_reports_of_other_scenarios_or_an_unknown_baseline_are_refused(tmp_path, capsys):
    a = report(tmp_path / "a", "A", [0.5, 0.6])
    b = report(tmp_path / "b", "B", [0.4, 0.4], scenario_text='{"other": 1}')
    with pytest.raises(SystemExit):
        paired.main([str(a), str(b), "--baseline", "B"])
    assert "scenario files differ" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        paired.main([str(a), "--baseline", "Z"])
    assert "allowed: ['A']" in capsys.readouterr().err


def seeds_report(folder: Path, flows_per_seed: dict[int, list[float]]) -> Path:
    (folder / "scenarios").mkdir(parents=True)
    rows = []
    for seed, flows in flows_per_seed.items():
        for i, flow in enumerate(flows):
            (folder / "scenarios" / f"scenario_{i:03d}.json").write_text("{}")
            rows.append({"planner": f"RL:seed_{seed}+shield", "scenario": f"scenario_{i:03d}.json",
                         "flow_rate": flow, "delay_mean": 1.0, "stop_ratio_all": 0.5})
    pd.DataFrame(rows).to_csv(folder / "metrics.csv", index=False)
    return folder


def test_labelled_reports_with_pooled_seeds_compare_sets_per_scenario(tmp_path, capsys):
    # Both sets name their planners RL:seed_N+shield; the labels keep them apart, and pooling
    # averages the seeds per scenario: tuned - default = mean(0.6, 0.8) - mean(0.4, 0.4) = 0.3.
    default = seeds_report(tmp_path / "d", {0: [0.4, 0.4], 1: [0.4, 0.4]})
    tuned = seeds_report(tmp_path / "t", {0: [0.6, 0.6], 1: [0.8, 0.8]})
    assert paired.main([f"default={default}", f"tuned={tuned}", "--pool-seeds", "--baseline",
                        "default:RL:seed_*+shield"]) == 0
    flow = [line for line in capsys.readouterr().out.splitlines() if "flow_rate" in line]
    assert len(flow) == 1
    fields = flow[0].split()
    assert fields[:2] == ["tuned:RL:seed_*+shield", "default:RL:seed_*+shield"]
    assert float(fields[3]) == 2 and float(fields[4]) == pytest.approx(0.3)
