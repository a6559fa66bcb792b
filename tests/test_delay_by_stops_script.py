"""scripts/delay_by_stops.py: per-vehicle delay changes grouped by who stopped, on a hand-made log."""

import importlib.util
from pathlib import Path

import pandas as pd
import pytest

SCRIPT = Path(__file__).parents[1] / "scripts" / "delay_by_stops.py"
spec = importlib.util.spec_from_file_location("delay_by_stops", SCRIPT)
delay_by_stops = importlib.util.module_from_spec(spec)
spec.loader.exec_module(delay_by_stops)


def vehicle(planner: str, vid: int, crossed: float | None, stopped: bool) -> dict:
    # delay = crossed - scheduled - free_flow = crossed - 10
    return {"planner": planner, "scenario": "s.json", "vehicle_id": vid, "scheduled": 0.0, "first_seen": 0.0,
            "free_flow": 10.0, "path_length": 100.0, "speed_limit": 10.0, "crossed": crossed, "stopped": stopped,
            "free_flow_covered": 10.0, "censored": None}  # fmt: skip


def test_groups_count_and_average_the_change_of_each_vehicle(tmp_path, capsys):
    log = pd.DataFrame([
        vehicle("B", 0, 12.0, True), vehicle("A", 0, 11.0, False),  # a stop avoided: -1 s
        vehicle("B", 1, 10.0, False), vehicle("A", 1, 13.0, False),  # slowed, not stopped: +3 s
        vehicle("B", 2, 10.0, False), vehicle("A", 2, 11.0, False),  # +1 s
        vehicle("B", 3, 10.0, False), vehicle("A", 3, None, False),  # not crossed under A: left out
    ])  # fmt: skip
    table = delay_by_stops.delay_by_stops(log, "A", "B")
    assert table.loc[(True, False), "vehicles"] == 1 and table.loc[(True, False), "delay_change"] == pytest.approx(-1)
    assert table.loc[(False, False), "vehicles"] == 2 and table.loc[(False, False), "delay_change"] == pytest.approx(2)
    assert table["share"].sum() == pytest.approx(1) and table.loc[(False, False), "share"] == pytest.approx(4 / 3)
    log.to_csv(tmp_path / "vehicles.csv", index=False)
    assert delay_by_stops.main([str(tmp_path), "--planner", "A", "--baseline", "C"]) == 2
    assert "planner 'C' is not in the report (it holds A, B)" in capsys.readouterr().err
