"""Bad input and failures around the SUMO plant: a missing extra is one line naming it; a SUMO error (a refused
insertion, a vehicle that vanished, a SUMO that died, a network it cannot load) fails its run in one line of the
report, without a traceback, and the other runs go on."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pandas as pd
import pytest

from envs.simulation.engine import PlantError
from envs.simulation.layouts import build_layout
from sb3_graph.cli import main

# 10 Hz: a configuration that no other test's harness has cached (a cached environment skips the check)
SUMO_CONFIG = '{"config": {"plant": "sumo", "simulation_frequency": 10}}'


@pytest.mark.parametrize(
    "argv",
    [
        ["evaluate", "--plant", "sumo", "--planner", "pr"],
        ["evaluate", "--plant", "builtin", "--plant", "sumo", "--planner", "pr"],
        ["evaluate", "--env-kwargs", SUMO_CONFIG, "--planner", "pr"],
        ["sweep", "--plant", "sumo", "--planner", "pr"],
        ["record", "--planner", "pr", "--env-kwargs", SUMO_CONFIG],
    ],
    ids=["evaluate-plant", "evaluate-two-plants", "evaluate-env-kwargs", "sweep", "record"],
)
def test_missing_sumo_is_one_line_naming_the_extra(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "libsumo", None)  # as if the sumo extra were not installed
    out = tmp_path / ("out.gif" if argv[0] == "record" else "out")
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert 'pip install "sb3-graph[sumo]"' in err and "Traceback" not in err
    assert not out.exists()


def _evaluate(tmp_path, *extra: str) -> tuple[int, pd.DataFrame, str]:
    """``evaluate --plant sumo`` in this process: glide+shield on 2 scenarios of 10 s (run seeds 4 and 5)."""
    out = tmp_path / "report"
    argv = ["evaluate", "--plant", "sumo", "--planner", "glide+shield", "--scenarios", "2", "--duration", "10"]
    code = main([*argv, "--seed", "4", "--jobs", "1", "--no-progress", "--out", str(out), *extra])
    return code, pd.read_csv(out / "metrics.csv").sort_values("run"), (out / "report.md").read_text()


def _assert_first_run_failed_in_one_line(code: int, runs: pd.DataFrame, report: str, pattern: str) -> None:
    assert code == 1
    assert runs["failed"].fillna(False).astype(bool).tolist() == [True, False]
    line = runs["planner_error"].iloc[0]
    assert "\n" not in line and "Traceback" not in line
    assert pd.Series([line]).str.fullmatch(r"plant error, scenario scenario_000\.json: " + pattern).all(), line
    assert line in report
    assert runs["steps"].iloc[1] == 50 and runs["vehicles"].iloc[1] > 0  # the other run went on, all 10 s of it


def test_a_failed_insertion_fails_its_run_in_one_line(tmp_path, monkeypatch):
    """SUMO refuses a ``vehicle.add`` (a libsumo error, here injected in the first run) in the middle of a run."""
    libsumo = pytest.importorskip("libsumo")
    from envs.simulation import sumo_plant

    insert = sumo_plant.SumoPlant._insert

    def refuse_vehicle_3(self, rows, front, speed):
        if self.seed == 4 and 3 in self.vehicle_id[rows]:
            raise libsumo.TraCIException("Invalid departPos for vehicle '3'.\nIt would lie off its lane.")
        insert(self, rows, front, speed)

    monkeypatch.setattr(sumo_plant.SumoPlant, "_insert", refuse_vehicle_3)
    code, runs, report = _evaluate(tmp_path)
    pattern = r"SUMO at t = \d+\.\d\d s: Invalid departPos for vehicle '3'\. It would lie off its lane\."
    _assert_first_run_failed_in_one_line(code, runs, report, pattern)


def test_a_dead_sumo_process_fails_its_run_in_one_line(tmp_path, monkeypatch):
    """A SUMO process that dies mid-run (killed for real: the runs talk to SUMO over TraCI, because a plant of this
    test holds the process's libsumo) fails that run; the plant closes without an error, the next run starts a
    new SUMO."""
    pytest.importorskip("libsumo")
    from envs.simulation import sumo_plant

    step = sumo_plant.SumoPlant.step

    def kill_at_2_s(self, acceleration, remove_collided=False):
        if self.seed == 4 and self.time >= 2.0 and self._sumo._process.poll() is None:
            self._sumo._process.kill()
            self._sumo._process.wait()
        return step(self, acceleration, remove_collided)

    monkeypatch.setattr(sumo_plant.SumoPlant, "step", kill_at_2_s)
    holder = sumo_plant.SumoPlant(build_layout("4way"))
    try:
        assert holder.backend == "libsumo"
        code, runs, report = _evaluate(tmp_path)
    finally:
        holder.close()
    _assert_first_run_failed_in_one_line(code, runs, report, r"SUMO at t = 2\.\d\d s: .+")


def test_a_sumo_process_that_cannot_load_fails_at_reset_in_one_line(tmp_path):
    """A SUMO process that cannot load its network (a broken file, here given to a second plant of the process,
    which runs SUMO as a process over TraCI) is a one-line :class:`PlantError` at reset; SUMO starts again
    afterwards. (libsumo itself crashes the process on a broken network: the SUMO plant hands it only networks
    that netconvert wrote.)"""
    pytest.importorskip("libsumo")
    from envs.simulation.sumo_plant import SumoPlant, network_of

    layout = build_layout("4way")
    bad = tmp_path / "broken.net.xml"
    bad.write_text("<net><edge id='a'")
    holder = SumoPlant(layout)
    try:
        with pytest.raises(PlantError, match=r"^SUMO at reset: \S") as caught:
            SumoPlant(layout, network=dataclasses.replace(network_of(layout), net_file=bad))
        assert "\n" not in str(caught.value)
        second = SumoPlant(layout)
        try:
            second.add(np.array([0]), np.array([5.0]), np.array([1]))
            second.step(np.zeros(1))
            assert second.backend == "traci" and second.num_vehicles == 1
        finally:
            second.close()
    finally:
        holder.close()


def test_a_vehicle_that_vanishes_is_reported_lost(monkeypatch):
    """A vehicle that SUMO drops during one of its steps (injected: removed as SUMO steps) leaves the rows as lost,
    with its reason, and the plant goes on with the others; the harness fails such a run in one line
    (``test_sumo_plant.test_a_lost_vehicle_fails_the_run_with_one_line``)."""
    libsumo = pytest.importorskip("libsumo")
    from envs.simulation.sumo_plant import SumoPlant

    layout = build_layout("4way")
    plant = SumoPlant(layout)
    try:
        assert plant.backend == "libsumo"
        r = layout.route_id("west->east")
        plant.add(np.array([r, r]), np.array([8.0, 8.0]), np.array([1, 2]), arc=np.array([40.0, 20.0]))
        plant.step(np.zeros(2))
        step = libsumo.simulation.step
        substeps = []

        def drop_vehicle_1_in_the_second_substep(*args):
            substeps.append(1)
            if len(substeps) == 2:  # as SUMO drops a vehicle itself (its subscription ends with it)
                libsumo.vehicle.unsubscribe("1")
                libsumo.vehicle.remove("1")
            return step(*args)

        monkeypatch.setattr(libsumo.simulation, "step", drop_vehicle_1_in_the_second_substep)
        events = plant.step(np.ones(2))
        assert events.lost.tolist() == [1] and plant.lost == {1: "SUMO removed it"}
        assert plant.vehicle_id.tolist() == [2]
        plant.step(np.ones(1))  # the plant goes on with the others
        assert plant.num_vehicles == 1 and plant.speed[0] > 8.0
    finally:
        plant.close()
