"""The fault model: its settings, its draws, the actuator (latency, lag), the perceived scene and the tracker."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401
from envs.evaluation.harness import run_episode
from envs.planners import make_planner
from envs.simulation.env import CoopIntersectionEnv
from envs.simulation.faults import FAULT_DEFAULTS, Actuator, FaultDraws, fault_config
from envs.simulation.traffic import demand_scenario

BOUNDS = {
    "position_sigma": 1.0,
    "position_bound": 3.0,
    "speed_sigma": 0.3,
    "speed_bound": 1.0,
    "loss": 0.05,
    "latency": 0.1,
    "lag": 0.3,
}


@pytest.mark.parametrize(
    "faults, entry",
    [
        ({"position_sigma": -1.0}, "position_sigma"),
        ({"speed_sigma": float("nan")}, "speed_sigma"),
        ({"loss": 1.5}, "loss"),
        ({"loss": -0.1}, "loss"),
        ({"max_age": 0.0}, "max_age"),
        ({"latency": 0.5}, "latency"),  # more than one policy period
        ({"lag": "slow"}, "lag"),
        ({"position_bound": 0.0}, "position_bound"),
        ({"tracker": "yes"}, "tracker"),
        ({"jitter": 1.0}, "jitter"),
    ],
)
def test_a_bad_fault_names_its_entry_and_range(faults, entry):
    with pytest.raises(ValueError, match=f"faults.*{entry}") as error:
        CoopIntersectionEnv(config={"faults": faults})
    assert "\n" not in str(error.value)
    if entry == "loss":
        assert "[0, 1]" in str(error.value)


def test_fault_settings_are_filled_in_and_infinite_bounds_are_none():
    cfg = CoopIntersectionEnv(config={"faults": {"loss": 0.05, "position_bound": math.inf}}).config["faults"]
    assert cfg == {**FAULT_DEFAULTS, "loss": 0.05, "position_bound": None}
    assert fault_config(None) == FAULT_DEFAULTS


def test_draws_belong_to_a_vehicle_and_a_step_not_to_the_scene():
    draws = FaultDraws(7)
    both = draws.normal(np.array([5, 9]), 3, 0)
    assert np.array_equal(draws.normal(np.array([9, 5]), 3, 0), both[::-1])
    assert np.array_equal(draws.normal(np.array([9]), 3, 0), both[1:])
    assert not np.array_equal(draws.normal(np.array([5, 9]), 4, 0), both)
    assert not np.array_equal(FaultDraws(8).normal(np.array([5, 9]), 3, 0), both)
    sample = draws.normal(np.arange(20_000), 1, 0)
    assert abs(sample.mean()) < 0.03 and abs(sample.std() - 1.0) < 0.03


def test_actuator_lag_and_latency():
    h = 1 / 15
    lagged = Actuator(latency=0.0, lag=0.3, substeps=3, h=h)
    ids = np.array([1])
    out = np.concatenate([lagged(ids, np.array([3.0])) for _ in range(30)])[:, 0]  # 6 s of a held command
    t = np.arange(1, out.size + 1) * h
    speed = np.cumsum(out) * h  # from rest: v(t) = c (t - tau (1 - exp(-t / tau)))
    assert np.allclose(speed, 3.0 * (t - 0.3 * (1 - np.exp(-t / 0.3))), atol=1e-9)
    late = Actuator(latency=0.1, lag=0.0, substeps=3, h=h)
    late(ids, np.array([2.0]))
    assert np.allclose(late(ids, np.array([-4.0]))[:, 0], [2.0, 0.5 * 2.0 + 0.5 * -4.0, -4.0])  # 1.5 sub-steps old
    assert np.allclose(late(np.array([2]), np.array([1.0]))[:, 0], [0.0, 0.5, 1.0])  # a new vehicle had command 0
    braked = Actuator(latency=0.0, lag=0.3, substeps=3, h=h)
    braked(ids, np.array([-5.0]))
    assert (braked(ids, np.array([5.0]), speed=np.array([0.0])) > 0).all()  # at rest its brakes held it, not -5
    braked(ids, np.array([-5.0]))
    assert braked(ids, np.array([5.0]), speed=np.array([3.0]))[0, 0] < 0  # moving: the braking unwinds first


def _stepped(config: dict, steps: int, seed: int = 3) -> tuple[list, list]:
    env = gym.make("CoopIntersection4Way-v0", config=config).unwrapped
    obs, _ = env.reset(seed=seed)
    observations, scenes = [obs], [(env.scene(), env.true_scene())]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        obs, *_ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        observations.append(obs)
        scenes.append((env.scene(), env.true_scene()))
    return observations, scenes


def test_no_fault_is_the_truth_itself_bitwise():
    plain_obs, plain = _stepped({}, 20)
    zero_obs, zero = _stepped({"faults": {"position_tau": 3.0, "tracker": False, "max_age": 2.0}}, 20)
    assert all(perceived is truth for perceived, truth in plain + zero)  # the same arrays, no copy
    for a, b in zip(plain_obs, zero_obs):
        assert all(np.array_equal(a[k], b[k]) for k in a)
    assert all(np.array_equal(a[0].arc, b[0].arc) for a, b in zip(plain, zero))
    assert plain[-1][0].arc_std is None and plain[-1][0].age is None


def test_latency_alone_shows_the_state_of_latency_ago_and_the_tracker_brings_it_to_now():
    faults = {"latency": 0.2, "tracker": False}
    _, raw = _stepped({"faults": faults, "spawn_probability": 0.0}, 6)
    perceived, truth = raw[-1]
    assert perceived is not truth and np.array_equal(perceived.vehicle_id, truth.vehicle_id)
    # 0.2 s is one policy period: the state at the start of the last step (the truth of one step before)
    before = {int(i): a for i, a in zip(raw[-2][1].vehicle_id, raw[-2][1].arc)}
    then = np.array([before[int(i)] for i in truth.vehicle_id])
    assert np.allclose(perceived.arc, np.clip(then, 0, None), atol=1e-9)
    assert np.allclose(perceived.age, 0.2)
    # Every derived field agrees with the perceived arc.
    shift = perceived.arc - truth.arc
    assert np.allclose(perceived.dist_to_entry, truth.dist_to_entry - shift)
    assert np.allclose(perceived.dist_to_exit, truth.dist_to_exit - shift)
    # The tracker's estimate is of when the coming commands take effect (now + latency: here the next step's end,
    # which the command in flight, the previous one, drives): nearly the truth one step later.
    _, tracked = _stepped({"faults": {**faults, "tracker": True}, "spawn_probability": 0.0}, 7)
    (est, _), (_, later) = tracked[-2], tracked[-1]
    stays = np.isin(est.vehicle_id, later.vehicle_id)
    assert np.abs(est.arc[stays] - later.arc[: stays.sum()]).max() < 0.05
    assert np.abs(perceived.arc - truth.arc).max() > 1.0


def test_lost_messages_are_held_and_never_older_than_max_age():
    _, scenes = _stepped({"faults": {"loss": 0.9, "max_age": 0.6, "tracker": False}}, 40)
    ages = np.concatenate([p.age for p, _ in scenes])
    assert ages.max() == pytest.approx(0.6) and (ages <= 0.6 + 1e-9).all() and (ages == 0).any()
    held = [p for p, _ in scenes[1:] if (p.age > 0).any()]
    assert held  # a held vehicle shows where it was: behind the truth by what it drove since
    p, t = scenes[-1]
    old = p.age > 0
    assert (p.arc[old] <= t.arc[old] + 1e-9).all()


def test_errors_are_bounded_correlated_and_paired():
    faults = {"position_sigma": 1.0, "position_bound": 1.5, "speed_sigma": 0.3, "speed_bound": 0.5, "tracker": False}
    _, scenes = _stepped({"faults": faults}, 60)
    _, first = _stepped({"faults": faults}, 60)
    err = np.concatenate([p.arc - t.arc for p, t in scenes])
    dv = np.concatenate([p.speed - t.speed for p, t in scenes])
    assert np.abs(err).max() <= 1.5 + 1e-9 and np.abs(err).max() > 1.0 and 0.6 < err.std() < 1.2
    assert np.abs(dv).max() <= 0.5 + 1e-9
    assert all(np.array_equal(a[0].arc, b[0].arc) for a, b in zip(first, scenes))  # reproducible
    # tau 1 s at 0.2 s steps: one step's error explains most of the next's (rho = exp(-0.2) = 0.82)
    a = {int(i): e for i, e in zip(scenes[30][0].vehicle_id, scenes[30][0].arc - scenes[30][1].arc)}
    b = {int(i): e for i, e in zip(scenes[31][0].vehicle_id, scenes[31][0].arc - scenes[31][1].arc)}
    common = sorted(set(a) & set(b))
    assert np.corrcoef([a[i] for i in common], [b[i] for i in common])[0, 1] > 0.5


def test_the_tracker_halves_a_white_speed_error():
    faults = {"speed_sigma": 1.0, "speed_tau": 0.0, "position_sigma": 0.5, "position_tau": 0.0}
    rms = {}
    for tracker in (False, True):
        _, scenes = _stepped({"faults": {**faults, "tracker": tracker}}, 60)
        dv = np.concatenate([p.speed - t.speed for p, t in scenes[10:]])
        rms[tracker] = float(np.sqrt(np.mean(dv**2)))
    assert rms[True] < 0.5 * rms[False]


def test_metrics_read_the_truth_and_a_run_is_reproducible():
    scenario = demand_scenario("4way", 20.0, 1, 0.4)
    env = gym.make("CoopIntersection4Way-v0", config={"collision_handling": "remove", "faults": BOUNDS})
    planner = make_planner("fullthrottle")
    log, facts = run_episode(env, planner, scenario, 20.0, seed=5)
    again, _ = run_episode(env, planner, scenario, 20.0, seed=5)
    assert log.equals(again)
    exact_env = gym.make("CoopIntersection4Way-v0", config={"collision_handling": "remove"})
    exact, _ = run_episode(exact_env, planner, scenario, 20.0, seed=5)
    assert not log.equals(exact)  # lag and latency changed how the vehicles drove


def test_the_tracker_beats_a_correlated_position_error_and_does_not_claim_better():
    faults = {"position_sigma": 1.0, "position_tau": 1.0, "speed_sigma": 0.3}
    rms, claimed = {}, {}
    for tracker in (False, True):
        _, scenes = _stepped({"faults": {**faults, "tracker": tracker}}, 80)
        err = np.concatenate([p.arc - t.arc for p, t in scenes[10:]])
        rms[tracker] = float(np.sqrt(np.mean(err**2)))
        claimed[tracker] = float(np.sqrt(np.mean(np.concatenate([p.arc_std for p, _ in scenes[10:]]) ** 2)))
    assert rms[True] < 0.85 * rms[False]
    assert claimed[True] >= rms[True]  # its standard deviation is no promise it cannot keep


def test_the_scene_carries_the_acceleration_the_lag_lets_each_vehicle_realise():
    env = gym.make("CoopIntersection4Way-v0", config={"faults": {"lag": 0.3}}).unwrapped
    env.reset(seed=2)
    assert np.array_equal(env.scene().acceleration, np.zeros(env.scene().num_vehicles))
    rng = np.random.default_rng(1)
    for _ in range(15):
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
    scene, plant = env.scene(), env.sim.actuator.memory
    rows, found = plant.find(scene.vehicle_id)
    truth = plant.get("realised", rows, found, 0.0)
    assert np.abs(truth).max() > 1.0 and np.allclose(scene.acceleration, truth)  # replayed from the commands
    assert CoopIntersectionEnv(config={}).default_config()["faults"]["lag"] == 0.0
