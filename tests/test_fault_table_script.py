"""scripts/fault_table.py: planners over fault levels, paired against full throttle behind the shield."""

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd

SCRIPT = Path(__file__).parents[1] / "scripts" / "fault_table.py"
spec = importlib.util.spec_from_file_location("fault_table", SCRIPT)
fault_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(fault_table)


def test_levels_scale_the_declared_bounds():
    assert fault_table.level_faults("none") == {}
    assert fault_table.level_faults("twice")["position_sigma"] == 2.0
    mild = fault_table.level_faults("mild")
    assert mild["latency"] == 0.05 and mild["position_tau"] == 1.0  # the correlation time is not scaled
    assert fault_table.level_faults("lag", {"lag": {"lag": 0.3}}) == {"lag": 0.3}


def test_the_table_pairs_each_level_and_perception_against_full_throttle(tmp_path, capsys):
    out = tmp_path / "runs.csv"
    argv = ["--planner", "glide+shield", "--demand", "0.4", "--custom", 'lag={"lag": 0.3}', "--perception", "raw"]
    assert fault_table.main([*argv, "--scenarios", "2", "--duration", "6", "--csv", str(out)]) == 0
    text = capsys.readouterr().out
    runs = pd.read_csv(out)
    assert set(runs["level"]) == {"none", "lag"} and set(runs["perception"]) == {"tracker", "raw"}
    assert len(runs) == 2 * 2 * 2  # (none, lag) x (full throttle, glide) x scenarios
    table = fault_table.fault_table(runs)
    glide = table[table["planner"] == "glide+shield"].set_index("level")
    baseline = runs[runs["planner"] == "fullthrottle+shield"].groupby("level")["flow_rate"].mean()
    mine = runs[runs["planner"] == "glide+shield"].groupby("level")["flow_rate"].mean()
    assert np.isclose(glide.loc["lag", "d_flow"], mine["lag"] - baseline["lag"])
    assert "| 0.4 | lag | raw | glide |" in text
    # the same runs, paired against glide instead (no run again)
    assert fault_table.main(["--runs", str(out), "--baseline", "glide+shield"]) == 0
    again = capsys.readouterr().out
    assert "Δ delay vs glide+shield" in again and "| 0.4 | lag | raw | glide | " in again
