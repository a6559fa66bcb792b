"""Crawling, hard braking and traction energy (envs.simulation.motion) on hand-computed trips, hand-built step
records and recorded tracks, and in a whole short evaluation run."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from envs.evaluation.metrics import VehicleLog, run_metrics, summarize
from envs.ind.mapping import track_motion
from envs.simulation import motion
from envs.simulation.motion import (
    AIR_DENSITY,
    DRAG_COEFFICIENT,
    FRONTAL_AREA,
    GEAR_SPEEDS,
    GRAVITY,
    ROLLING_RESISTANCE_F0,
    ROLLING_RESISTANCE_F1,
    ROTATING_MASS_FACTORS,
    VEHICLE_LOADING,
    VEHICLE_MASS,
    WHEEL_ROTATING_MASS,
    event_starts,
    traction_energy,
)
from envs.simulation.scene import MAJOR, STOP_SPEED, STRAIGHT, Scene
from envs.simulation.step_record import StepRecord

H = 1.0 / 15.0  # the environments' sub-step [s]
ROAD_MASS = VEHICLE_MASS + VEHICLE_LOADING
DRAG = 0.5 * AIR_DENSITY * DRAG_COEFFICIENT * FRONTAL_AREA  # [kg/m]


def _cruise_power(v: float) -> float:
    """Rolling and air resistance times speed [W]: the power of driving at constant speed ``v``."""
    return (ROAD_MASS * GRAVITY * (ROLLING_RESISTANCE_F0 + ROLLING_RESISTANCE_F1 * v) + DRAG * v**2) * v


def _trip(*legs: tuple[float, float]) -> np.ndarray:
    """Speeds at the sub-step boundaries of legs ``(duration [s], speed at the leg's end [m/s])``, each leg
    at constant acceleration from the previous leg's end speed (the first leg starts at its own end speed)."""
    speeds = [legs[0][1]]
    for duration, end in legs:
        steps = round(duration / H)
        speeds.extend(np.linspace(speeds[-1], end, steps + 1)[1:])
    return np.array(speeds)


def _energy(speeds: np.ndarray) -> float:
    return float(traction_energy(speeds[:-1], speeds[1:], H).sum())


def test_energy_of_a_constant_speed_trip_is_the_road_load_times_the_time():
    v, seconds = 12.0, 30.0
    expected = (ROAD_MASS * GRAVITY * (ROLLING_RESISTANCE_F0 + ROLLING_RESISTANCE_F1 * v) + DRAG * v**2) * v * seconds
    assert _energy(_trip((seconds, v))) == pytest.approx(expected, rel=1e-12)


def test_energy_of_one_stop_and_restart():
    """Cruise at 10 m/s, brake to a stop, stand, restart at 1 m/s^2 to 3 m/s, cruise: braking and standing
    cost nothing (no recuperation), the restart costs the inertia of first gear plus the road load."""
    brake, accel, restart = -2.0, 1.0, 3.0  # [m/s^2], [m/s^2], [s]
    speeds = _trip((2.0, 10.0), (5.0, 0.0), (3.0, 0.0), (restart, accel * restart), (4.0, accel * restart))
    first_gear = VEHICLE_MASS * ROTATING_MASS_FACTORS[0] + WHEEL_ROTATING_MASS + VEHICLE_LOADING
    assert accel * restart < GEAR_SPEEDS[1] and ROTATING_MASS_FACTORS[1] == ROTATING_MASS_FACTORS[0]  # first gear
    assert VEHICLE_MASS * ROTATING_MASS_FACTORS[-1] * brake * 10 + _cruise_power(10.0) < 0  # braking: no traction
    v1 = accel * restart
    restart_energy = (
        first_gear * v1**2 / 2  # kinetic energy, rotating masses included
        + ROAD_MASS * GRAVITY * ROLLING_RESISTANCE_F0 * accel * restart**2 / 2  # rolling over the distance
        + ROAD_MASS * GRAVITY * ROLLING_RESISTANCE_F1 * accel**2 * restart**3 / 3  # integral of v^2
        + DRAG * accel**3 * restart**4 / 4  # integral of v^3
    )
    expected = _cruise_power(10.0) * 2.0 + restart_energy + _cruise_power(v1) * 4.0
    assert _energy(speeds) == pytest.approx(expected, rel=1e-12)
    # The stop costs: the same trip without it (cruising at 10 m/s throughout the 17 s) is cheaper per metre.
    assert restart_energy > 4 * _cruise_power(v1)


def test_only_positive_wheel_power_counts():
    assert traction_energy(np.array([10.0]), np.array([5.0]), 1.0)[0] == 0.0  # -5 m/s^2
    coast = traction_energy(np.array([10.0]), np.array([9.9]), 1.0)[0]  # -0.1 m/s^2: less than the road load
    assert 0 < coast < _cruise_power(10.0)


def test_hard_braking_events_are_maximal_runs_of_one_vehicle():
    flag = np.array([1, 1, 0, 1, 0, 0, 1, 1, 1], bool)
    vehicle = np.array([1, 1, 1, 1, 1, 2, 2, 3, 3])
    assert event_starts(flag, vehicle).tolist() == [1, 0, 0, 1, 0, 0, 1, 1, 0]  # a new vehicle starts a new run
    assert motion.hard_braking(np.array([-3.0, -3.0 - 1e-9, -3.04, -3.06, -5.0])).tolist() == [0, 0, 0, 1, 1]


def _scene(ids, speeds, time):
    n = len(ids)
    return Scene(
        time=time,
        dt=0.2,
        vehicle_id=np.array(ids, np.int64),
        route=np.zeros(n, np.int64),
        s=np.zeros(n),
        position=np.zeros((n, 2)),
        heading=np.zeros(n),
        speed=np.array(speeds, float),
        speed_limit=np.full(n, 15.0),
        dist_to_entry=np.full(n, 30.0),
        dist_to_exit=np.full(n, 50.0),
        leader=np.full(n, -1),
        gap=np.full(n, np.inf),
        priority=np.full(n, MAJOR),
        maneuver=np.full(n, STRAIGHT),
        length=np.full(n, 5.0),
        route_names=("south->north",),
        conflicts=np.zeros((1, 1), bool),
    )


def _steps(**profiles):
    """Per vehicle id ``v<id>``: speeds at the sub-step boundaries of consecutive policy steps (3 sub-steps each)."""
    ids = np.array([int(name[1:]) for name in profiles])
    speeds = np.array([_trip(*legs) for legs in profiles.values()]).T  # (3 k + 1, n)
    return ids, speeds


def test_vehicle_log_counts_crawlers_hard_brakes_and_energy_to_the_crossing():
    ids, speeds = _steps(
        v1=((1.2, 0.5),),  # crawls at 0.5 m/s: slow, not stopped
        v2=((0.2, 10.0), (0.2, 8.0), (0.2, 8.0), (0.2, 6.0), (0.4, 6.0)),  # two hard brakings (-10 m/s^2)
        v3=((0.2, 10.0), (0.4, 8.8), (0.2, 8.8), (0.4, 7.6)),  # brakes at -3 m/s^2: not hard
        v4=((0.2, 10.0), (0.4, 10.0 - 0.4 * 3.3), (0.6, 10.0 - 0.4 * 3.3)),  # -3.3 m/s^2 across two steps: one
    )
    log = VehicleLog()
    for k in range(6):  # six policy steps of 0.2 s
        rows = speeds[3 * k : 3 * k + 4]
        log.observe(_scene(ids, rows[0], 0.2 * k))
        crossed = [2] if k == 2 else []  # vehicle 2 crosses in the third step
        log.record(StepRecord(time=0.2 * (k + 1), crossed=crossed, moved=ids, speeds=rows, substep=H))
    log.finish(_scene(ids, speeds[-1], 1.2))
    frame = log.frame().set_index("vehicle_id")
    assert frame["min_speed"].tolist() == pytest.approx([0.5, 6.0, 7.6, 8.68])
    assert frame["hard_brakes"].tolist() == [0, 2, 0, 1]
    assert not frame["stopped"].any()
    assert frame.loc[2, "traction_energy_j"] == pytest.approx(_energy(speeds[:10, 1]))  # up to the third step's end
    assert frame.loc[2, "traction_energy_j"] < _energy(speeds[:, 1])
    assert frame[["traction_energy_j"]].drop(2).isna().all().all()  # no crossing: left out
    row = run_metrics(log.frame(), duration=1.2)
    assert row["slow_ratio"] == 0.25 and row["stop_ratio_all"] == 0.0
    assert row["hard_brakes_per_vehicle"] == 0.75
    assert row["energy_kj_per_vehicle"] == pytest.approx(frame.loc[2, "traction_energy_j"] / 1000)
    pooled = summarize(pd.DataFrame({"planner": ["A"], "flow_rate": [0.1]}), log.frame().assign(planner="A"))["A"]
    assert pooled["slow_ratio"] == 0.25 and pooled["hard_brakes_per_vehicle"] == 0.75


def test_logs_without_motion_leave_the_new_columns_undefined():
    log = VehicleLog()
    log.observe(_scene([1], [5.0], 0.0))
    log.record(StepRecord(time=0.2))
    row = run_metrics(log.frame(), duration=0.2)
    assert row["slow_ratio"] == 0.0  # the scenes' speeds are known
    assert np.isnan(row["hard_brakes_per_vehicle"]) and np.isnan(row["energy_kj_per_vehicle"])


def test_recorded_tracks_are_measured_like_simulated_ones():
    rate = 25.0
    v = _trip((2.0, 10.0), (0.4, 8.0), (1.0, 8.0), (0.4, 6.0), (2.0, 6.0))  # two hard brakings, -5 m/s^2
    v = np.interp(np.arange(0, len(v) * H, 1 / rate), np.arange(len(v)) * H, v)  # resampled at 25 Hz
    crawl = np.full(50, 0.5)
    tracks = pd.DataFrame(
        {
            "trackId": np.r_[np.full(len(v), 4), np.full(len(crawl), 7)],
            "frame": np.r_[np.arange(len(v)), np.arange(len(crawl)) + 10],
            "speed": np.r_[v, crawl],
        }
    )
    starts, energy = track_motion(tracks, rate)
    assert starts[: len(v)].sum() == 2 and starts[len(v) :].sum() == 0
    assert energy[0] == 0 and energy[len(v)] == 0  # each track from its first frame
    assert energy[len(v) - 1] == pytest.approx(traction_energy(v[:-1], v[1:], 1 / rate).sum())
    assert energy[-1] == pytest.approx(_cruise_power(0.5) * 49 / rate)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    import torch

    from envs.evaluation.harness import evaluate, generate_scenarios

    torch.set_num_threads(1)
    scenarios = generate_scenarios(tmp_path_factory.mktemp("motion"), 1, 30.0, 4, "4way", demand=0.4)
    planners = [("fullthrottle+shield", "FT+S"), ("aim", "AIM")]
    return evaluate(planners, scenarios, "CoopIntersection4Way-v0", 30.0, progress=False)


def test_a_whole_run_has_the_new_columns_finite_and_in_range(short_run):
    runs, vehicles = short_run
    for _, row in runs.iterrows():
        assert 0 <= row["stop_ratio_all"] <= row["slow_ratio"] <= 1
        assert 0 <= row["hard_brakes_per_vehicle"] <= 30 / H / 2  # at most one event per two sub-steps
        assert 0 < row["energy_kj_per_vehicle"] < np.inf
    # Per vehicle: stopped is exactly a lowest speed under the stop threshold; energy only for crossed vehicles,
    # and at most full power for the whole time in the scene.
    assert ((vehicles["min_speed"] < STOP_SPEED) == vehicles["stopped"]).all()
    assert vehicles["hard_brakes"].notna().all() and (vehicles["hard_brakes"] >= 0).all()
    crossed = vehicles["crossed"].notna()
    assert vehicles.loc[crossed, "traction_energy_j"].gt(0).all()
    assert vehicles.loc[~crossed, "traction_energy_j"].isna().all()
    ceiling = motion.wheel_power(20.0, 5.0) * (vehicles["crossed"] - vehicles["first_seen"] + 0.2)
    assert (vehicles.loc[crossed, "traction_energy_j"] <= ceiling[crossed]).all()


def test_the_environment_records_the_executed_sub_step_speeds():
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    env = gym.make("CoopIntersection4Way-v0")
    base = env.unwrapped
    env.reset(seed=3)
    governed = 0
    for _ in range(40):
        before = base.scene()
        _, _, terminated, truncated, info = env.step(np.ones(env.action_space.shape))  # full throttle asked
        record, after = info["record"], base.scene()
        assert record.moved.tolist() == before.vehicle_id.tolist() and record.substep == pytest.approx(H)
        assert record.speeds.shape == (4, before.vehicle_id.size)
        np.testing.assert_array_equal(record.speeds[0], before.speed)
        kept = np.isin(after.vehicle_id, record.moved)
        column = {vid: k for k, vid in enumerate(record.moved.tolist())}
        np.testing.assert_array_equal(record.speeds[-1, [column[v] for v in after.vehicle_id[kept]]], after.speed[kept])
        # what happened, not what was asked: a vehicle the governor held back accelerated less than asked
        held = [column[v] for v in record.governed.tolist()]
        assert (np.diff(record.speeds[:, held], axis=0).min(axis=0, initial=np.inf) < 5.0 * H - 1e-9).all()
        governed += len(held)
        if terminated or truncated:
            break
    assert governed > 0


def test_the_ind_replay_reports_the_recorded_drivers_motion(tmp_path):
    from envs.commands.ind import dataset_runs
    from envs.ind.loader import load_recordings
    from envs.ind.mapping import map_recordings
    from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording

    write_recording(tmp_path, make_recording(9, default_vehicles(seed=9, num=30), SyntheticSite()))
    recordings = load_recordings(tmp_path, [9])
    mapped = map_recordings(recordings)
    runs, vehicles = dataset_runs(mapped, recordings)
    tracks = mapped.mapped
    row = runs.iloc[0]
    assert row["slow_ratio"] == pytest.approx((tracks["min_speed"] < motion.SLOW_SPEED).mean())
    assert 0 < row["stop_ratio_all"] <= row["slow_ratio"] < 1  # every stopped driver was slow
    assert row["hard_brakes_per_vehicle"] == tracks["hard_brakes"].mean()
    assert row["energy_kj_per_vehicle"] == pytest.approx(tracks["energy_to_centre_j"].mean() / 1000)
    assert tracks["energy_to_centre_j"].gt(0).all()
    assert vehicles["traction_energy_j"].tolist() == tracks["energy_to_centre_j"].tolist()
