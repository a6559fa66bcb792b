"""Eclipse SUMO as the second plant: the generated network, parity with our plant, the seam, bad input."""

from __future__ import annotations

import sys

import numpy as np
import pytest

pytest.importorskip("libsumo")
pytest.importorskip("sumolib")

from envs.simulation.config import validate_config  # noqa: E402
from envs.simulation.engine import Simulation  # noqa: E402
from envs.simulation.env import CoopIntersectionEnv  # noqa: E402
from envs.simulation.layouts import LAYOUT_NAMES, build_layout  # noqa: E402
from envs.simulation.plant import Plant, make_plant  # noqa: E402
from envs.simulation.sumo_network import FILE_NAMES, write_network  # noqa: E402
from envs.simulation.sumo_plant import SumoPlant, libsumo_module, network_of  # noqa: E402
from envs.simulation.traffic import ScenarioTraffic, generate_scenario  # noqa: E402


@pytest.fixture
def plant_4way():
    plant = SumoPlant(build_layout("4way"))
    yield plant
    plant.close()


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_network_stop_lines_and_exits_agree(name):
    """Along every route's SUMO lanes (internal lanes included), its stop line and its exit lie where the layout
    has them, within 0.1 m."""
    layout = build_layout(name)
    net = network_of(layout)
    assert len(net.route_edges) == layout.num_routes
    assert np.abs(net.stop_arc - layout.entry_arc).max() < 0.1
    assert np.abs(net.exit_arc - layout.exit_arc).max() < 0.1


def test_network_never_overwrites_a_file(tmp_path):
    (tmp_path / FILE_NAMES[0]).write_text("mine")
    with pytest.raises(ValueError, match="exists already"):
        write_network(build_layout("3way"), tmp_path)
    assert (tmp_path / FILE_NAMES[0]).read_text() == "mine"
    net = write_network(build_layout("3way"), tmp_path / "fresh")
    assert net.net_file.is_file()


def _parity(name: str, duration: float, seed: int) -> tuple[float, float, int]:
    """Our plant at SUMO's step and the SUMO plant, one scenario, the same random accelerations, no humans:
    the largest difference of arcs and speeds, of SUMO's own front bumpers from ours, and the vehicles seen."""
    layout = build_layout(name)
    scenario = generate_scenario(layout, duration, seed)
    ours = Simulation(layout, simulation_frequency=20)
    sumo = SumoPlant(layout, simulation_frequency=20)
    try:
        traffic = [ScenarioTraffic(layout, scenario), ScenarioTraffic(layout, scenario)]
        for plant, t in zip((ours, sumo), traffic):
            t.spawn(plant)
        rng = np.random.default_rng(seed)
        worst_state = worst_front = 0.0
        seen: set[int] = set()
        while ours.time < duration - 1e-9:
            acc = rng.uniform(-3.0, 5.0, ours.num_vehicles)
            for plant, t in zip((ours, sumo), traffic):
                plant.step(acc)
                t.spawn(plant)
            assert np.array_equal(ours.vehicle_id, sumo.vehicle_id)
            inserted = sumo.in_sumo
            worst_state = max(
                worst_state,
                np.abs(ours.arc - sumo.arc).max(initial=0.0),
                np.abs(ours.speed - sumo.speed).max(initial=0.0),
            )
            # SUMO's front bumper against ours, where the layout's samples hold the front: its pose interpolates
            # with a spacing of ds, which the last, shorter interval of a route does not have.
            front = ours.arc + ours.length / 2
            inside = inserted & (front <= layout.length[ours.route] - layout.ds)
            xy, _ = layout.pose(ours.route[inside], front[inside])
            worst_front = max(worst_front, np.abs(sumo.front_position[inside] - xy).max(initial=0.0))
            seen.update(ours.vehicle_id.tolist())
        assert not sumo.lost
        return worst_state, worst_front, len(seen)
    finally:
        sumo.close()


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_parity_with_our_plant_100_s(name):
    """The same accelerations move every vehicle the same way in both plants over 100 s (about 1.5 s a layout):
    SUMO's own front bumpers within 0.05 m of ours."""
    state, front, seen = _parity(name, 100.0, seed=11)
    assert seen >= 30
    assert state < 1e-6
    assert front < 0.05


def test_a_second_plant_runs_over_traci(plant_4way):
    """libsumo holds one simulation per process: a second plant starts SUMO as its own process over TraCI and moves
    the vehicles exactly as the first; once both are closed, the next plant uses libsumo again."""
    layout = build_layout("4way")
    second = SumoPlant(layout)
    try:
        assert (plant_4way.backend, second.backend) == ("libsumo", "traci")
        scenario = generate_scenario(layout, 20.0, 1)
        traffic = [ScenarioTraffic(layout, scenario), ScenarioTraffic(layout, scenario)]
        for plant, t in zip((plant_4way, second), traffic):
            t.spawn(plant)
        rng = np.random.default_rng(1)
        while second.time < 20.0 - 1e-9:
            acc = rng.uniform(-3.0, 5.0, second.num_vehicles)
            for plant, t in zip((plant_4way, second), traffic):
                plant.step(acc)
                t.spawn(plant)
            assert np.array_equal(plant_4way.vehicle_id, second.vehicle_id)
            assert np.array_equal(plant_4way.arc, second.arc)
    finally:
        second.close()
    plant_4way.close()
    again = SumoPlant(layout)
    assert again.backend == "libsumo"
    again.close()


def test_both_plants_implement_the_seam(plant_4way):
    layout = build_layout("4way")
    config = validate_config({"plant": "builtin"}, CoopIntersectionEnv.default_config())
    assert isinstance(make_plant(layout, config), Simulation)
    assert isinstance(plant_4way, Plant)
    assert isinstance(make_plant(layout, config), Plant)


def test_plant_config_is_checked():
    defaults = CoopIntersectionEnv.default_config()
    with pytest.raises(ValueError, match="config key 'plant' must be one of"):
        validate_config({"plant": "carla"}, defaults)
    with pytest.raises(ValueError, match="'simulation_frequency' must divide 1000 with plant 'sumo'"):
        validate_config({"plant": "sumo"}, defaults)  # 15 Hz: 66.7 ms is no SUMO step
    assert validate_config({"plant": "sumo", "simulation_frequency": 10}, defaults)["plant"] == "sumo"


def test_missing_sumo_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "libsumo", None)
    with pytest.raises(ImportError, match=r"sb3-graph\[sumo\]"):
        libsumo_module()


def test_insertion_inside_the_junction_is_refused(plant_4way):
    layout = build_layout("4way")
    r = layout.route_id("west->north")
    with pytest.raises(ValueError, match="inside a junction"):
        plant_4way.add(np.array([r]), np.array([5.0]), np.array([7]), arc=np.array([layout.entry_arc[r] + 3.0]))


def test_humans_are_sumo_drivers(plant_4way):
    """A human row ignores the command (SUMO's driver keeps going where a connected vehicle brakes to a stop)."""
    layout = build_layout("4way")
    r = layout.route_id("west->east")
    plant_4way.add(np.array([r, r]), np.array([8.0, 8.0]), np.array([1, 2]), arc=np.array([40.0, 10.0]),
                   human=np.array([True, False]))  # fmt: skip
    for _ in range(15):
        plant_4way.step(np.full(plant_4way.num_vehicles, -5.0))
    assert plant_4way.speed[1] == 0.0
    assert plant_4way.speed[0] > 5.0


def test_env_on_sumo_reports_collisions_from_sumo():
    """Full throttle through a busy junction collides, and SUMO's junction check sees it; behind the shield the
    same scenario runs without collisions."""
    scenario = generate_scenario("4way", 30.0, 5, rate_range=(0.4, 0.4))
    counts = {}
    for shield in (False, True):
        env = CoopIntersectionEnv(
            {"plant": "sumo", "simulation_frequency": 20, "collision_handling": "remove", "shield": shield}
        )
        try:
            env.reset(options={"scenario": scenario})
            assert isinstance(env.unwrapped.sim, SumoPlant)
            collisions, done = 0, False
            while not done:
                _, _, terminated, truncated, info = env.step(np.ones(env.action_space.shape, np.float32))
                collisions += len(info["record"].collisions)
                done = terminated or truncated
            counts[shield] = collisions
        finally:
            env.close()
    assert counts[False] > 0
    assert counts[True] == 0


def test_with_plant_sets_the_config_and_names_the_extra(monkeypatch):
    from envs.commands.evaluate import with_plant
    from sb3_graph.commands import UserError

    assert with_plant(None, None) is None
    assert with_plant(None, "sumo") == {"config": {"plant": "sumo", "simulation_frequency": 20}}
    kept = with_plant({"config": {"simulation_frequency": 10}}, "sumo")
    assert kept["config"] == {"plant": "sumo", "simulation_frequency": 10}
    with pytest.raises(UserError, match="--plant must be one of"):
        with_plant(None, "carla")
    monkeypatch.setitem(sys.modules, "libsumo", None)
    with pytest.raises(UserError, match=r"--plant sumo: .*sb3-graph\[sumo\]"):
        with_plant(None, "sumo")


def test_evaluate_on_sumo_end_to_end(tmp_path):
    """``evaluate --plant sumo`` in this process: a report, SUMO's collisions counted for full throttle, none
    behind the shield, no vehicle lost; and the process may open another SUMO plant afterwards."""
    import pandas as pd

    from sb3_graph.cli import main

    out = tmp_path / "report"
    args = ["evaluate", "--plant", "sumo", "--planner", "fullthrottle", "--planner", "glide+shield", "--out", str(out)]
    assert main([*args, "--scenarios", "2", "--duration", "30", "--seed", "4", "--jobs", "1", "--no-progress"]) == 0
    runs = pd.read_csv(out / "metrics.csv")
    assert set(runs["planner"]) == {"FullThrottle", "Glide+shield"}
    assert runs.loc[runs["planner"] == "FullThrottle", "collided"].sum() > 0
    assert runs.loc[runs["planner"] == "Glide+shield", "collided"].sum() == 0
    assert (runs["lost_vehicles"] == 0).all()
    SumoPlant(build_layout("4way")).close()


def test_building_an_environment_holds_no_sumo():
    """highway-env's constructor resets once; the SUMO plant it made is let go, so that a second environment
    (``record`` after ``evaluate``'s config check) can run in the same process."""
    config = {"plant": "sumo", "simulation_frequency": 20}
    first, second = CoopIntersectionEnv(config), CoopIntersectionEnv(config)
    try:
        second.reset(seed=0)
        second.step(np.zeros(second.action_space.shape, np.float32))
    finally:
        second.close()
        first.close()


def test_a_refused_insertion_is_reported_not_hidden(plant_4way):
    """A human vehicle placed where SUMO's insertion check refuses it (overlapping a standing one) leaves the rows
    as lost, with its reason, and SUMO does not insert it later. (A connected vehicle, in speed mode 0, is
    inserted wherever it is put.)"""
    layout = build_layout("4way")
    r = layout.route_id("west->east")
    plant_4way.add(np.array([r]), np.array([0.0]), np.array([1]), arc=np.array([40.0]))
    plant_4way.step(np.zeros(1))
    plant_4way.add(np.array([r]), np.array([5.0]), np.array([2]), arc=np.array([38.0]), human=True)
    events = plant_4way.step(np.zeros(2))
    assert events.lost.tolist() == [2] and 2 in events.removed
    assert plant_4way.lost == {2: "SUMO did not insert it"}
    assert plant_4way.vehicle_id.tolist() == [1]
    plant_4way.step(np.zeros(1))
    assert plant_4way._sumo.vehicle.getIDList() == ("1",)


def test_a_lost_vehicle_fails_the_run_with_one_line(tmp_path, monkeypatch):
    """Fault injection: SUMO never receives vehicle 0, so the plant reports it lost; ``evaluate`` counts the run as
    failed with one line naming the scenario and the vehicle, and goes on."""
    import pandas as pd

    from envs.simulation import sumo_plant
    from sb3_graph.cli import main

    insert = sumo_plant.SumoPlant._insert

    def drop_vehicle_0(self, rows, front, speed):
        keep = self.vehicle_id[rows] != 0
        insert(self, rows[keep], front[keep], speed[keep])

    monkeypatch.setattr(sumo_plant.SumoPlant, "_insert", drop_vehicle_0)
    out = tmp_path / "report"
    args = ["evaluate", "--plant", "sumo", "--planner", "glide+shield", "--out", str(out), "--no-progress"]
    assert main([*args, "--scenarios", "2", "--duration", "10", "--seed", "4", "--jobs", "1"]) == 1  # failed runs
    runs = pd.read_csv(out / "metrics.csv")
    assert runs["failed"].all()
    assert (runs["lost_vehicles"] == 1).all()
    assert runs["planner_error"].str.fullmatch(r"plant error, scenario scenario_00\d\.json: 1 vehicles lost, the "
                                               r"first: id 0, SUMO did not insert it").all()  # fmt: skip


def test_runs_repeat_and_the_seed_reaches_sumos_drivers():
    """The same scenario and seed give the same trajectories; another seed draws other drivers (speed factors)."""
    scenario = generate_scenario("4way", 20.0, 2, human_share=1.0)

    def arcs(seed: int) -> list[np.ndarray]:
        env = CoopIntersectionEnv({"plant": "sumo", "simulation_frequency": 20, "collision_handling": "remove"})
        try:
            env.reset(seed=seed, options={"scenario": scenario})
            out = []
            for _ in range(60):
                env.step(np.zeros(env.action_space.shape, np.float32))
                out.append(env.unwrapped.sim.arc.copy())
            return out
        finally:
            env.close()

    first, again, other = arcs(1), arcs(1), arcs(2)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert any(a.shape != b.shape or not np.array_equal(a, b) for a, b in zip(first, other))
