"""Training spawns, evaluation scenarios, scenario files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from envs.simulation.engine import Simulation
from envs.simulation.layouts import build_layout
from envs.simulation.traffic import Scenario, ScenarioTraffic, TrainingTraffic, generate_scenario


def test_generated_scenario_follows_the_rates_and_headways():
    lay = build_layout("4way")
    scenario = generate_scenario(lay, duration=3600.0, rng=5, min_headway=1.0)
    assert scenario.seed == 5 and scenario.layout == "4way"
    assert (np.diff(scenario.time) >= 0).all() and scenario.vehicle_id.tolist() == list(
        range(scenario.num_vehicles)
    )
    route = np.array([lay.route_id(r) for r in scenario.route])
    lane = lay.route_spawn_lane[route]
    rate = scenario.meta["rate_major"]
    assert 0.2 <= rate <= 0.4 and scenario.meta["rate_minor"] == pytest.approx(rate / 2)
    for k in range(len(lay.spawn_lanes)):
        t = scenario.time[lane == k]
        assert np.diff(t).min() >= 1.0 - 1e-9  # the shift of the exponential
        expected = 3600.0 * rate * (1.0 if lay.spawn_priority[k] == 1 else 0.5)
        assert abs(t.size - expected) < 5 * np.sqrt(expected)  # Poisson-like count
    limit = lay.speed_limit[route, 0]
    assert ((scenario.speed >= 0.6 * limit - 1e-9) & (scenario.speed <= limit + 1e-9)).all()
    # Destinations: every route of the layout is used over an hour.
    assert set(scenario.route) == set(lay.route_names)


def test_generation_is_reproducible_and_validated():
    a = generate_scenario("3way", 100.0, np.random.default_rng(1))
    b = generate_scenario("3way", 100.0, np.random.default_rng(1))
    assert a.route == b.route and np.array_equal(a.time, b.time) and np.array_equal(a.speed, b.speed)
    with pytest.raises(ValueError, match="rate_range"):
        generate_scenario("3way", 100.0, 0, rate_range=(0.4, 0.2))
    with pytest.raises(ValueError, match="min_headway"):
        generate_scenario("3way", 100.0, 0, rate_range=(0.5, 1.0), min_headway=2.0)


def test_save_load_round_trip(tmp_path):
    scenario = generate_scenario("inD", 60.0, 3)
    path = scenario.save(tmp_path / "s.json")
    loaded = Scenario.load(path)
    assert loaded.to_dict() == scenario.to_dict()
    with pytest.raises(FileExistsError):
        scenario.save(path)  # never overwrite silently
    scenario.save(path, overwrite=True)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d.pop("vehicles"), "missing field 'vehicles'"),
        (lambda d: d.update(layout="roundabout"), "field 'layout'"),
        (lambda d: d.update(duration=-1), "field 'duration'"),
        (lambda d: d["vehicles"][1].update(route="north->north"), r"vehicles\[1\]\.route"),
        (lambda d: d["vehicles"][0].update(time=-3.0), r"vehicles\[0\]\.time"),
        (lambda d: d["vehicles"][0].update(speed="fast"), r"vehicles\[0\]\.speed must be a number"),
        (lambda d: d["vehicles"][2].pop("id"), r"vehicles\[2\] is missing field 'id'"),
        (lambda d: d["vehicles"][2].update(colour="red"), r"vehicles\[2\] has unknown fields"),
        (lambda d: d["vehicles"][1].update(id=d["vehicles"][0]["id"]), "field 'id' must be unique"),
    ],
)
def test_bad_scenario_file_is_a_clear_error(tmp_path, mutate, match):
    data = generate_scenario("4way", 30.0, 0).to_dict()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=match) as err:
        Scenario.load(path)
    assert str(path) in str(err.value)


def test_unreadable_scenario_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        Scenario.load(tmp_path / "missing.json")
    bad = tmp_path / "broken.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON") as err:
        Scenario.load(bad)
    assert "broken.json" in str(err.value)


def test_training_traffic_spawns_where_free():
    lay = build_layout("4way")
    sim = Simulation(lay)
    traffic = TrainingTraffic(lay, spawn_probability=1.0)
    rng = np.random.default_rng(0)
    ids = traffic.spawn(sim, rng)
    assert ids.tolist() == [0, 1, 2, 3] and sim.num_vehicles == 4
    assert sorted(lay.route_spawn_lane[sim.route].tolist()) == [0, 1, 2, 3]
    limit = lay.speed_limit[sim.route, 0]
    assert ((sim.speed >= 0.6 * limit) & (sim.speed <= limit)).all()
    assert traffic.spawn(sim, rng).size == 0  # the spawn points are occupied
    assert TrainingTraffic(lay, spawn_probability=0.0).spawn(Simulation(lay), rng).size == 0


def test_training_traffic_respects_capacity():
    lay = build_layout("inD")
    sim = Simulation(lay, max_vehicles=2)
    traffic = TrainingTraffic(lay, spawn_probability=1.0)
    assert traffic.spawn(sim, np.random.default_rng(0)).size == 2 and sim.num_vehicles == 2


def test_scenario_appearances_wait_for_space():
    lay = build_layout("4way")
    scenario = Scenario(
        layout="4way", duration=20.0, seed=None, vehicle_id=[7, 8, 9], time=[0.0, 0.0, 0.5],
        route=("south->north", "south->east", "west->east"), speed=[8.0, 8.0, 9.0],
        length=[5.0] * 3, width=[2.0] * 3,
    )  # fmt: skip
    sim = Simulation(lay)
    traffic = ScenarioTraffic(lay, scenario)
    assert traffic.spawn(sim).tolist() == [7] and traffic.waiting == 1  # 8 waits behind 7
    appeared = {7: 0.0}
    for _ in range(20):
        sim.step(np.zeros(sim.num_vehicles))
        for i in traffic.spawn(sim):
            appeared[int(i)] = sim.time
    assert appeared[9] == pytest.approx(0.6)  # first policy step at or after 0.5 s
    assert appeared[8] > 0.6  # waited until 7 had moved on far enough
    assert traffic.waiting == 0
    with pytest.raises(ValueError, match="layout"):
        ScenarioTraffic(build_layout("3way"), scenario)
