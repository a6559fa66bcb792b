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
