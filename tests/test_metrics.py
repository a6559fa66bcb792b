"""Metrics on hand-made vehicle logs and step records with known stops, crossings and collisions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.metrics import VehicleLog, add_travel_times, governor_share, run_metrics, summarize, vehicle_frame
from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT, Scene
from envs.simulation.step_record import StepRecord


def _vehicle(
    vid,
    priority,
    maneuver,
    crossed=np.nan,
    stopped=False,
    collided=False,
    first_seen=0.0,
    path_length=100.0,
    speed_limit=10.0,
):
    return dict(
        vehicle_id=vid,
        route="r",
        priority=priority,
        maneuver=maneuver,
        first_seen=first_seen,
        path_length=path_length,
        speed_limit=speed_limit,
        crossed=crossed,
        removed=np.nan,
        stopped=stopped,
        collided=collided,
    )


@pytest.fixture
def log() -> pd.DataFrame:
    return vehicle_frame(
        [
            _vehicle(1, "major", "straight", crossed=10.0),  # free flow: 100 m at 10 m/s in 10 s
            _vehicle(2, "major", "left", crossed=16.0, stopped=True),  # 6 s delay
            _vehicle(3, "minor", "right", crossed=14.0, stopped=True, first_seen=2.0),  # 2 s delay
            _vehicle(4, "minor", "straight", stopped=True),  # still queued at the end
            _vehicle(5, "minor", "left", collided=True),
            _vehicle(6, "major", "straight", collided=True),
        ]
    )


def test_run_metrics(log):
    row = run_metrics(log, duration=20.0)
    assert row["vehicles"] == 6 and row["crossed"] == 3
    assert row["flow_rate"] == pytest.approx(3 / 20.0)
    assert row["stop_ratio_all"] == pytest.approx(3 / 6)
    assert row["stop_ratio_major"] == pytest.approx(1 / 3) and row["vehicles_major"] == 3
    assert row["stop_ratio_minor"] == pytest.approx(2 / 3) and row["vehicles_minor"] == 3
    assert row["stop_ratio_left"] == pytest.approx(1 / 2)
    assert row["stop_ratio_right"] == pytest.approx(1.0) and row["vehicles_right"] == 1
    assert row["stop_ratio_straight"] == pytest.approx(1 / 3)
    assert row["collision_rate"] == pytest.approx(2 / 6) and row["collided"] == 2
    assert row["delay_mean"] == pytest.approx((0 + 6 + 2) / 3)
    assert row["delay_median"] == pytest.approx(2.0)
    assert row["travel_time_mean"] == pytest.approx((10 + 16 + 12) / 3)
    with pytest.raises(ValueError, match="duration"):
        run_metrics(log, duration=0.0)


def test_travel_times_only_for_crossed(log):
    timed = add_travel_times(log)
    assert timed["delay"].notna().sum() == 3
    assert np.isnan(timed.loc[timed["vehicle_id"] == 4, "travel_time"]).all()


def test_summarize_pools_vehicles_and_takes_flow_quantiles(log):
    runs = pd.DataFrame({"planner": ["A", "A", "A", "B"], "flow_rate": [0.1, 0.2, 0.4, 0.3]})
    vehicles = pd.concat([log.assign(planner="A"), log.iloc[:2].assign(planner="B")], ignore_index=True)
    summary = summarize(runs, vehicles)
    assert set(summary) == {"A", "B"}
    a = summary["A"]
    assert a["runs"] == 3 and a["vehicles"] == 6
    assert a["flow_rate"]["median"] == pytest.approx(0.2)
    assert a["flow_rate"]["q1"] == pytest.approx(0.15) and a["flow_rate"]["q3"] == pytest.approx(0.3)
    assert a["flow_rate"]["mean"] == pytest.approx(0.7 / 3)
    assert set(a["stop_ratio"]) == {"all", "major", "minor", "left", "straight", "right"}
    assert a["collision_rate"] == pytest.approx(2 / 6)
    assert a["delay_s"]["median"] == pytest.approx(2.0)
    assert summary["B"]["stop_ratio"]["minor"] is None  # no minor vehicle: undefined, not 0


def _scene(ids, speeds, time, dist_to_exit):
    n = len(ids)
    return Scene(
        time=time,
        dt=0.5,
        vehicle_id=np.array(ids, dtype=np.int64),
        route=np.array([0, 0, 1][:n], dtype=np.int64),
        s=np.zeros(n),
        position=np.zeros((n, 2)),
        heading=np.zeros(n),
        speed=np.array(speeds, float),
        speed_limit=np.full(n, 10.0),
        dist_to_entry=np.array(dist_to_exit, float) - 20,
        dist_to_exit=np.array(dist_to_exit, float),
        leader=np.full(n, -1),
        gap=np.full(n, np.inf),
        priority=np.array([MAJOR, MINOR, MINOR][:n]),
        maneuver=np.array([STRAIGHT, RIGHT, LEFT][:n]),
        length=np.full(n, 5.0),
        route_names=("south->north", "west->east"),
        conflicts=np.zeros((2, 2), bool),
    )


def test_vehicle_log_from_records_and_scenes():
    """What a vehicle is comes from the first scene it is in; what happened to it from the step records."""
    log = VehicleLog()
    log.observe(_scene([7, 8], [10.0, 5.0], 0.0, [52.5, 80.0]))  # centre 50 m before the exit
    log.record(StepRecord(time=0.5, entered=[9], stopped=[8]))
    log.observe(_scene([7, 8, 9], [10.0, 0.1, 8.0], 0.5, [47.5, 80.0, 90.0]))
    log.record(StepRecord(time=5.0, crossed=[7], collisions=np.array([[8, 9]])))
    log.record(StepRecord(time=6.0, crossed=[7], removed=[7]))
    frame = log.frame().set_index("vehicle_id")
    assert list(frame.index) == [7, 8, 9]
    assert frame.loc[7, "crossed"] == 5.0  # the first crossing counts
    assert frame.loc[7, "removed"] == 6.0
    assert frame.loc[7, "path_length"] == 50.0 and frame.loc[7, "priority"] == "major"
    assert not frame.loc[7, "stopped"] and frame.loc[8, "stopped"]
    assert frame.loc[9, "route"] == "west->east" and frame.loc[9, "first_seen"] == 0.5
    assert frame.loc[9, "priority"] == "minor" and frame.loc[9, "maneuver"] == "left"
    assert frame.loc[8, "collided"] and frame.loc[9, "collided"] and not frame.loc[7, "collided"]
    row = run_metrics(log.frame(), duration=6.0)
    assert row["crossed"] == 1 and row["collision_rate"] == pytest.approx(2 / 3)
    assert row["delay_mean"] == pytest.approx(0.0)  # 50 m at 10 m/s, crossed after 5 s


def test_step_record_coerces_hand_built_ids_and_names_the_collided():
    record = StepRecord(time=1.0, crossed=[3, 4], collisions=[[9, 2], [2, 5]])
    assert record.crossed.dtype == np.int64 and record.stopped.shape == (0,)
    assert record.collisions.shape == (2, 2) and record.collided.tolist() == [2, 5, 9]
    info = record.info()
    assert info["record"] is record and info["collided"] is record.collided and info["time"] == 1.0
    # equal by value (gymnasium's checker compares two runs of one seeded step)
    assert record == StepRecord(time=1.0, crossed=np.array([3, 4]), collisions=np.array([[9, 2], [2, 5]]))
    assert record != StepRecord(time=1.0, crossed=[3, 4]) and record != info


def test_delay_from_the_scheduled_time_and_unspawned_vehicles_count():
    log = vehicle_frame(
        [
            # appeared 2 s late (spawn blocked), then drove in free flow: the 2 s are its delay
            dict(_vehicle(1, "major", "straight", crossed=13.0, first_seen=3.0), scheduled=1.0, free_flow=10.0),
            # never appeared: stopped, delay from its scheduled appearance to the end of the run
            dict(_vehicle(2, "minor", "left", first_seen=np.nan, stopped=True), scheduled=15.0, spawned=False,
                 censored=20.0, free_flow=10.0, free_flow_covered=0.0),
            # still on its way at the end: the delay so far, against the free-flow time of what it covered
            dict(_vehicle(3, "major", "left", first_seen=10.0), scheduled=10.0, censored=20.0, free_flow=10.0,
                 free_flow_covered=4.0),
        ]
    )  # fmt: skip
    timed = add_travel_times(log).set_index("vehicle_id")
    assert timed.loc[1, "delay"] == pytest.approx(2.0) and timed.loc[1, "travel_time"] == pytest.approx(12.0)
    assert timed.loc[2, "delay"] == pytest.approx(5.0) and np.isnan(timed.loc[2, "travel_time"])
    assert timed.loc[3, "delay"] == pytest.approx(6.0)
    row = run_metrics(log, duration=20.0)
    assert row["vehicles"] == row["vehicles_scheduled"] == 3 and row["not_spawned"] == 1
    assert row["stop_ratio_all"] == pytest.approx(1 / 3) and row["stop_ratio_minor"] == pytest.approx(1.0)
    assert row["delay_mean"] == pytest.approx((2 + 5 + 6) / 3)
    assert row["flow_rate"] == pytest.approx(1 / 20) and row["offered_flow"] == pytest.approx(2 / 20)


def test_speed_limit_violations_per_vehicle_step():
    log = VehicleLog()
    for time, speeds in ((0.0, [10.05, 10.2]), (0.5, [10.11, 12.0]), (1.0, [9.0, 10.3])):
        log.observe(_scene([7, 8], speeds, time, [52.5, 80.0]))  # limit 10 m/s
    log.finish(_scene([7, 8], [15.0, 15.0], 1.5, [40.0, 70.0]))  # no planner step follows: not counted
    frame = log.frame().set_index("vehicle_id")
    assert frame.loc[7, "speed_violations"] == 1 and frame.loc[8, "speed_violations"] == 3
    assert run_metrics(log.frame(), duration=1.5)["speed_limit_violations"] == 4


def test_governor_share_counts_held_back_vehicle_steps():
    env = gym.make("CoopIntersection4Way-v0", config={"spawn_probability": 0.0, "initial_spawn_probability": 0.0})
    env.reset(seed=0)
    base = env.unwrapped
    lay = base.layout
    r = lay.route_id("south->east")  # a right turn: 5.2 m/s in the curve
    base.place_vehicles([r, lay.route_id("west->east")], [lay.entry_arc[r] - 3.0, 20.0], [9.0, 2.0], [0, 1])
    log = VehicleLog(lay)
    for k in range(3):
        log.observe(base.scene())
        _, _, _, _, info = env.step(np.ones(env.action_space.shape, np.float32))  # full throttle
        log.record(info["record"] if k else info)  # the record, or the info that carries it
    frame = log.frame()
    steps = frame.set_index("vehicle_id")
    # The turning vehicle is held back every step; the slow straight one accelerates freely.
    assert steps.loc[0, "governed_steps"] == 3 and steps.loc[1, "governed_steps"] == 0
    assert governor_share(frame) == pytest.approx(3 / 6)
