"""scripts/liveness.py finds runs in which traffic stopped moving."""

import importlib.util
from pathlib import Path

import pandas as pd

SCRIPT = Path(__file__).parents[1] / "scripts" / "liveness.py"
spec = importlib.util.spec_from_file_location("liveness", SCRIPT)
liveness = importlib.util.module_from_spec(spec)
spec.loader.exec_module(liveness)


def test_a_run_without_a_late_crossing_and_with_waiting_vehicles_is_stuck(tmp_path, capsys):
    runs = pd.DataFrame(
        {
            "planner": ["A", "A", "B"],
            "run": [0, 1, 0],
            "duration_s": [100.0, 100.0, 100.0],
            "waiting_at_end": [3, 2, 0],
            "collided": [0, 1, 0],
            "vehicles_scheduled": [10, 10, 10],
            "flow_rate": [0.3, 0.1, 0.0],
        }
    )
    vehicles = pd.DataFrame(
        {"planner": ["A", "A", "B"], "run": [0, 1, 0], "crossed": [95.0, 50.0, float("nan")]}
    )
    runs.to_csv(tmp_path / "metrics.csv", index=False)
    vehicles.to_csv(tmp_path / "vehicles.csv", index=False)
    table = liveness.liveness(tmp_path, window=10.0).set_index("planner")
    stuck = table.columns[-1]
    assert table.loc["A", stuck] == 1  # run 1: last crossing at 50 s, vehicles waiting
    assert table.loc["B", stuck] == 0  # nothing crossed, but nothing waits either
    assert table.loc["A", "collided"] == 1 and table.loc["A", "lowest_flow"] == 0.1
    assert liveness.main([str(tmp_path)]) == 0 and "stuck_runs" in capsys.readouterr().out
