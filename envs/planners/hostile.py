"""Hostile planners: the attacks on the safety shield and on the harness that its table in docs/shield.md runs.

Each one tries a way to break the evaluation from the only place a planner sits: the scene it is
handed and the array it returns. Run them by class name behind the shield, e.g.
``sb3-graph evaluate --planner envs.planners.hostile:BoxParker --shield``;
``scripts/hostile_table.py`` runs them all on every layout.

- :class:`SceneEditor` writes into every array of its scene (to blind the shield) and drives at full throttle.
- :class:`LayoutEditor` tries to raise the speed limits of the shared layout (to change the physics for
  everyone) and drives at full throttle.
- :class:`CollisionSeeker` times each vehicle to reach the intersection together with a crossing one.
- :class:`ZoneMeeter` times each vehicle to reach its conflict zone together with the conflicting vehicle whose
  arrival there is closest to its own, rams any leader within reach and brakes every other vehicle.
- :class:`Fuzzer` answers random accelerations, held for a random number of steps per vehicle.
- :class:`BrakeChecker` drives at full throttle and brakes hard every few seconds.
- :class:`BoxParker` stops every vehicle that is inside the intersection (to stall it).
- :class:`BangBang` alternates full throttle and full braking every step.
- :class:`NaNPlanner` answers NaN for one vehicle every step (an invalid output).
- :class:`Crawler` keeps every vehicle before its line just above the standing speed: the junction starves
  without a vehicle ever standing.
- :class:`LineHolder` holds every vehicle before the stop line forever: the shield's rules inside the
  intersection do not cover it; its watchdog hands the stalled junction to a live planner
  (:mod:`envs.planners.watchdog`, docs/shield.md).
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from envs.planners.base import Planner
from envs.simulation.scene import Scene


def _inside(scene: Scene) -> np.ndarray:
    """``(n,)`` bool: past the stop line and not yet out of the intersection area."""
    return (scene.dist_to_entry < 0) & (scene.dist_to_exit > 0)


class SceneEditor(Planner):
    """Overwrites every array of the scene it is handed (speeds 0, positions far away, no leaders, no
    conflicts, ...), tries the layout's arrays too, and commands full throttle.

    :attr:`writes` counts the writes that went through (into the planner's own copy only),
    :attr:`refused` those the read-only layout refused.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "SceneEditor") -> None:
        super().__init__(name)
        self.writes = 0
        self.refused = 0

    def act(self, scene: Scene) -> np.ndarray:
        for f in fields(scene):
            value = getattr(scene, f.name)
            if isinstance(value, np.ndarray) and value.size:
                try:
                    value[...] = -1 if value.dtype.kind in "iub" else 1e6
                    self.writes += 1
                except ValueError:
                    self.refused += 1
        if scene.layout is not None:
            self.refused += _attack_layout(scene.layout)
        return np.full(scene.num_vehicles, float(scene.a_max))


def _attack_layout(layout) -> int:
    """Try to make every array of a layout writable and raise its speed limits; the refused attempts."""
    refused = 0
    for name, value in list(vars(layout).items()):
        if not isinstance(value, np.ndarray):
            continue
        for target in (value, value.base):
            try:
                if isinstance(target, np.ndarray):
                    target.setflags(write=True)
            except ValueError:
                refused += 1
        try:
            value[...] = 20.0 if name in ("speed_limit",) else value
        except ValueError:
            refused += 1
    try:
        layout.speed_limit = np.full_like(layout.speed_limit, 20.0)
    except AttributeError:
        refused += 1
    return refused


class LayoutEditor(Planner):
    """Tries to set every speed limit of the shared layout to 20 m/s (``speed_limit[:] = 20``, through
    ``setflags``, its base, and by replacing the attribute), then commands full throttle.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "LayoutEditor") -> None:
        super().__init__(name)
        self.refused = 0

    def act(self, scene: Scene) -> np.ndarray:
        if scene.layout is not None:
            self.refused += _attack_layout(scene.layout)
        return np.full(scene.num_vehicles, float(scene.a_max))


class CollisionSeeker(Planner):
    """Times every approaching vehicle to reach the intersection together with the crossing vehicle
    whose arrival is closest to its own (throttle when later, brake when earlier); full throttle
    inside and after.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "CollisionSeeker") -> None:
        super().__init__(name)

    def act(self, scene: Scene) -> np.ndarray:
        n = scene.num_vehicles
        acc = np.full(n, float(scene.a_max))
        if n < 2:
            return acc
        arrival = np.maximum(scene.dist_to_entry, 0.0) / np.maximum(scene.speed, 0.5)
        partner = scene.conflicts[scene.route[:, None], scene.route[None, :]] & scene.approaching[None, :]
        spread = np.where(partner, np.abs(arrival[:, None] - arrival[None, :]), np.inf)
        target = spread.argmin(axis=1)
        has = np.isfinite(spread[np.arange(n), target]) & (scene.dist_to_entry > 0)
        early = arrival < arrival[target]
        acc[has & early] = float(scene.a_min)
        return acc


class ZoneMeeter(Planner):
    """Times each vehicle to arrive at its conflict zone together with the conflicting vehicle whose arrival at
    their shared zone is closest to its own: full throttle when later, gentle braking when earlier; rams any
    leader within ``ram_gap``; brakes every other vehicle (those with neither a partner nor a leader in reach).

    Arrivals are read from the layout's conflict zones (:attr:`envs.simulation.layouts.Layout.zone_start`) at
    the current speed; without a layout the planner brakes every vehicle.

    :param name: the name shown in reports
    :param ram_gap: bumper gap below which a vehicle accelerates into its leader [m]
    :param gentle: the braking when early [m/s^2, positive]
    """

    def __init__(self, name: str = "ZoneMeeter", ram_gap: float = 12.0, gentle: float = 1.0) -> None:
        super().__init__(name)
        self.ram_gap = float(ram_gap)
        self.gentle = float(gentle)

    def act(self, scene: Scene) -> np.ndarray:
        n = scene.num_vehicles
        acc = np.full(n, float(scene.a_min))
        if n == 0 or scene.layout is None or scene.arc is None:
            return acc
        route, arc = scene.route, scene.arc
        start = scene.layout.zone_start[route[:, None], route[None, :]]  # (n, n): i's zone with j, on i's route
        end = scene.layout.zone_end[route[:, None], route[None, :]]
        conflict = scene.conflicts[route[:, None], route[None, :]] & (route[:, None] != route[None, :])
        ahead = start - (arc + scene.length / 2)[:, None]  # front to the zone's start [m]
        open_zone = conflict & ((end - (arc - scene.length / 2)[:, None]) > 0)  # its rear not yet past the zone
        with np.errstate(invalid="ignore"):
            arrival = np.where(open_zone, np.maximum(ahead, 0.0), np.inf) / np.maximum(scene.speed, 0.5)[:, None]
            mine, theirs = arrival, arrival.T  # [i, j]: i's arrival at its zone with j, and j's at the same zone
            spread = np.where(open_zone & open_zone.T & (ahead > 0), np.abs(mine - theirs), np.inf)
        target = spread.argmin(axis=1)
        rows = np.arange(n)
        has = np.isfinite(spread[rows, target])
        late = mine[rows, target] >= theirs[rows, target]
        acc[has & late] = float(scene.a_max)
        acc[has & ~late] = -self.gentle
        acc[(scene.leader >= 0) & (scene.gap < self.ram_gap)] = float(scene.a_max)
        return acc


class Fuzzer(Planner):
    """Random accelerations: each vehicle draws a command uniformly within the bounds and holds it for a number
    of steps of its own (1 to ``hold``), so that it both rams and brakes at random moments. The draws are a
    hash of the seed given to ``reset``, the vehicle's id and the step: reproducible, and vectorized.

    :param name: the name shown in reports
    :param hold: most steps a drawn command is held
    """

    def __init__(self, name: str = "Fuzzer", hold: int = 10) -> None:
        super().__init__(name)
        self.hold = int(hold)
        self.seed = 0
        self.steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.seed = int(seed or 0)
        self.steps = 0

    def act(self, scene: Scene) -> np.ndarray:
        key = _mix(scene.vehicle_id.astype(np.uint64) ^ _mix(np.full(1, self.seed, np.uint64)))
        held = 1 + (key % np.uint64(self.hold)).astype(np.int64)
        epoch = (self.steps // held).astype(np.uint64)
        self.steps += 1
        u = (_mix(key ^ (epoch * np.uint64(0x9E3779B97F4A7C15))) >> np.uint64(11)).astype(float) / float(1 << 53)
        return float(scene.a_min) + u * float(scene.a_max - scene.a_min)


def _mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser over an array of ``uint64`` (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


class BrakeChecker(Planner):
    """Full throttle, except that every vehicle with an even id brakes at ``a_min`` for the first
    ``brake`` seconds of every ``period`` seconds.

    :param name: the name shown in reports
    :param period: cycle length [s]
    :param brake: braking time per cycle [s]
    """

    def __init__(self, name: str = "BrakeChecker", period: float = 3.0, brake: float = 1.0) -> None:
        super().__init__(name)
        self.period = float(period)
        self.brake = float(brake)

    def act(self, scene: Scene) -> np.ndarray:
        acc = np.full(scene.num_vehicles, float(scene.a_max))
        if (scene.time % self.period) < self.brake:
            acc[scene.vehicle_id % 2 == 0] = float(scene.a_min)
        return acc


class BoxParker(Planner):
    """Brakes every vehicle inside the intersection area to a standstill; full throttle elsewhere.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "BoxParker") -> None:
        super().__init__(name)

    def act(self, scene: Scene) -> np.ndarray:
        return np.where(_inside(scene), float(scene.a_min), float(scene.a_max))


class BangBang(Planner):
    """Every vehicle alternates full throttle and full braking from one step to the next.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "BangBang") -> None:
        super().__init__(name)
        self.steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.steps = 0

    def act(self, scene: Scene) -> np.ndarray:
        self.steps += 1
        value = scene.a_max if self.steps % 2 else scene.a_min
        return np.full(scene.num_vehicles, float(value))


class NaNPlanner(Planner):
    """Full throttle, but NaN for one vehicle of every scene (a different row each step): an invalid
    output every step.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "NaNPlanner") -> None:
        super().__init__(name)
        self.steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.steps = 0

    def act(self, scene: Scene) -> np.ndarray:
        acc = np.full(scene.num_vehicles, float(scene.a_max))
        if scene.num_vehicles:
            acc[self.steps % scene.num_vehicles] = np.nan
        self.steps += 1
        return acc


class LineHolder(Planner):
    """Holds every vehicle that can still stop before the stop line there, forever; full throttle for
    the others. Behind the shield its traffic moves only through the watchdog's takeovers
    (:mod:`envs.planners.watchdog`); with ``Shield(watchdog_after=None)`` it stands for good.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "LineHolder") -> None:
        super().__init__(name)

    def act(self, scene: Scene) -> np.ndarray:
        a = float(scene.a_max)
        can_stop = scene.dist_to_entry - scene.speed**2 / (2 * a) > 0.5
        return np.where(can_stop | (scene.speed < 1e-6) & (scene.dist_to_entry > 0), -a, a)


class Crawler(Planner):
    """Brakes every vehicle before its stop line to ``speed`` (just above
    :data:`envs.simulation.scene.STOP_SPEED`, so that none ever stands) and holds it there; full throttle past
    the line. Its traffic reaches the line minutes late, never waiting in the standing sense.

    :param name: the name shown in reports
    :param speed: the crawl [m/s]
    """

    def __init__(self, name: str = "Crawler", speed: float = 0.4) -> None:
        super().__init__(name)
        self.speed = float(speed)

    def act(self, scene: Scene) -> np.ndarray:
        a = float(scene.a_max)
        before = scene.dist_to_entry > 0
        hold = np.clip((self.speed - scene.speed) / float(scene.dt), -a, a)
        return np.where(before, hold, a)
