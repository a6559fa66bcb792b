"""Traffic: the training spawner and the evaluation scenarios (paper, section "Experiments").

- Training (:class:`TrainingTraffic`): on every spawn lane with enough free space a vehicle
  appears with probability ``p`` per policy step (a curriculum raises ``p`` until it saturates
  at 5 %); the destination is uniform over the routes of that lane; the initial speed is uniform
  in ``[60 %, 100 %]`` of the lane's speed limit.
- Evaluation (:class:`Scenario`, :func:`generate_scenario`, :class:`ScenarioTraffic`): a table of
  appearances (time, route, speed, id) generated per spawn lane with shifted-exponential
  inter-arrival times, rate uniform in ``[0.2, 0.4]`` veh/s per major-road lane and half of it per
  minor-road lane (:func:`demand_scenario` fixes the rate instead, for the demand sweep). In
  simulation an appearance waits while its spawn position is not free; at most one vehicle
  appears per lane and policy step. Scenario files are JSON
  (:meth:`Scenario.save`, :meth:`Scenario.load`) and replay exactly: the same planner actions give
  the same trajectories.
- Mixed traffic (``human_share``): each scheduled vehicle is human-driven with that
  probability (:func:`human_flags`), drawn from the scenario's seed with a random stream of its own,
  so that a share of 0 draws nothing and leaves every other draw as it was. Human drivers follow
  the static priority rules (:class:`envs.planners.priority_rules.PriorityRulesPlanner`) inside the
  simulation; a planner's command for them is ignored. Files store the flag per vehicle (format
  version 2); version-1 files read as all automated.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from envs.simulation.engine import Simulation
from envs.simulation.layouts import Layout
from envs.simulation.sumo_junction import LAYOUT_HELP, is_layout_name, named_layout

SCENARIO_FORMAT = "sb3-graph-scenario"
SCENARIO_VERSION = 2
SCENARIO_VERSIONS = (1, 2)  # readable; version 1 has no "human" field (all automated)
VEHICLE_FIELDS = ("id", "time", "route", "speed", "length", "width", "human")
# Tag of the human-driver random stream: the flags come from ``default_rng([HUMAN_STREAM, seed])``,
# never from the stream that draws the arrivals, so a share of 0 changes no other draw.
HUMAN_STREAM = 0x48554D414E
# Bounds of a scenario file (docs/security.md): a file from someone else cannot ask for
# a run that never ends, a vehicle larger than a lane, or more memory than a machine has.
MAX_DURATION = 86_400.0  # one simulated day [s]
MAX_VEHICLES = 100_000
MAX_FILE_BYTES = 64 << 20
VEHICLE_BOUNDS = {"time": MAX_DURATION, "speed": 100.0, "length": 30.0, "width": 5.0}  # [s], [m/s], [m], [m]


@dataclass
class Scenario:
    """An evaluation scenario: who appears where and when.

    :param layout: layout name (one of ``envs.simulation.layouts.LAYOUT_NAMES``)
    :param duration: episode length [s]; the episode is truncated when it is reached
    :param seed: seed the scenario was generated from (informative), or ``None``
    :param vehicle_id: ``(k,)`` int64 unique ids
    :param time: ``(k,)`` appearance times [s], not negative
    :param route: route name of each vehicle, e.g. ``"south->north"``
    :param speed: ``(k,)`` initial speeds [m/s], not negative
    :param length: ``(k,)`` vehicle lengths [m]
    :param width: ``(k,)`` vehicle widths [m]
    :param meta: free-form information (e.g. the drawn rates), saved with the file
    :param human: ``(k,)`` bool: the vehicle is human-driven (the planner cannot command it);
        default all automated
    """

    layout: str
    duration: float
    seed: int | None
    vehicle_id: np.ndarray
    time: np.ndarray
    route: tuple[str, ...]
    speed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    human: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vehicle_id = np.asarray(self.vehicle_id, np.int64).reshape(-1)
        self.time = np.asarray(self.time, float).reshape(-1)
        self.route = tuple(str(r) for r in self.route)
        self.speed = np.asarray(self.speed, float).reshape(-1)
        self.length = np.asarray(self.length, float).reshape(-1)
        self.width = np.asarray(self.width, float).reshape(-1)
        if self.human is None:
            self.human = np.zeros(self.vehicle_id.shape[0], bool)
        self.human = np.asarray(self.human, bool).reshape(-1)
        self.duration = float(self.duration)
        self.validate()

    @property
    def num_vehicles(self) -> int:
        return int(self.vehicle_id.shape[0])

    def validate(self, source: str = "scenario") -> None:
        """Check every field; raise ``ValueError`` naming ``source`` and the field."""
        if not is_layout_name(self.layout):
            raise ValueError(f"{source}: field 'layout' must be {LAYOUT_HELP}, got {self.layout!r}")
        if not (math.isfinite(self.duration) and 0 < self.duration <= MAX_DURATION):
            raise ValueError(
                f"{source}: field 'duration' must be a number of seconds in (0, {MAX_DURATION:g}], got {self.duration}"
            )
        k = self.vehicle_id.shape[0]
        if k > MAX_VEHICLES:
            raise ValueError(f"{source}: field 'vehicles' holds {k} vehicles, more than the {MAX_VEHICLES} accepted")
        for name in ("time", "speed", "length", "width", "human"):
            if getattr(self, name).shape[0] != k:
                raise ValueError(
                    f"{source}: field '{name}' has {getattr(self, name).shape[0]} entries, expected {k}"
                )
        if len(self.route) != k:
            raise ValueError(f"{source}: field 'route' has {len(self.route)} entries, expected {k}")
        if np.unique(self.vehicle_id).size != k:
            raise ValueError(f"{source}: field 'id' must be unique per vehicle")
        for name, lower, strict in (
            ("time", 0.0, False),
            ("speed", 0.0, False),
            ("length", 0.0, True),
            ("width", 0.0, True),
        ):
            values = getattr(self, name)
            upper = VEHICLE_BOUNDS[name]
            bad = ~np.isfinite(values) | ((values <= lower) if strict else (values < lower)) | (values > upper)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                low = "(" if strict else "["
                raise ValueError(
                    f"{source}: vehicles[{i}].{name} must be a number in {low}{lower:g}, {upper:g}], got {values[i]}"
                )
        routes = set(named_layout(self.layout).route_names)
        for i, r in enumerate(self.route):
            if r not in routes:
                raise ValueError(
                    f"{source}: vehicles[{i}].route {r!r} is not a route of layout {self.layout!r}; "
                    f"allowed: {sorted(routes)}"
                )

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready content of a scenario file."""
        vehicles = [
            {
                "id": int(i),
                "time": float(t),
                "route": r,
                "speed": float(v),
                "length": float(a),
                "width": float(b),
                "human": bool(h),
            }
            for i, t, r, v, a, b, h in zip(
                self.vehicle_id, self.time, self.route, self.speed, self.length, self.width, self.human
            )
        ]
        return {
            "format": SCENARIO_FORMAT,
            "version": SCENARIO_VERSION,
            "layout": self.layout,
            "duration": self.duration,
            "seed": self.seed,
            "meta": self.meta,
            "vehicles": vehicles,
        }

    def save(self, path: str | Path, overwrite: bool = False) -> Path:
        """Write the scenario as JSON.

        :param path: file to write
        :param overwrite: replace an existing file (by default an existing file is an error)
        :return: the path written
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def from_dict(cls, data: Any, source: str = "scenario") -> Scenario:
        """Build and validate a scenario from the content of a scenario file.

        :param data: the parsed JSON
        :param source: name used in error messages (the file)
        :raises ValueError: naming ``source`` and the offending field
        """
        if not isinstance(data, dict):
            raise ValueError(f"{source}: expected a JSON object at the top level, got {type(data).__name__}")
        if data.get("format", SCENARIO_FORMAT) != SCENARIO_FORMAT:
            raise ValueError(
                f"{source}: field 'format' must be {SCENARIO_FORMAT!r}, got {data.get('format')!r}"
            )
        version = data.get("version", SCENARIO_VERSION)
        if isinstance(version, bool) or version not in SCENARIO_VERSIONS:
            raise ValueError(
                f"{source}: field 'version' must be one of {list(SCENARIO_VERSIONS)}, got {data.get('version')!r}"
            )
        fields_ = VEHICLE_FIELDS if version >= 2 else VEHICLE_FIELDS[:-1]
        for key in ("layout", "duration", "vehicles"):
            if key not in data:
                raise ValueError(f"{source}: missing field {key!r}")
        if not isinstance(data["layout"], str):
            raise ValueError(f"{source}: field 'layout' must be a string, got {data['layout']!r}")
        duration = data["duration"]
        if isinstance(duration, bool) or not isinstance(duration, (int, float)) or not _fits_float(duration):
            raise ValueError(f"{source}: field 'duration' must be a number, got {duration!r}")
        seed = data.get("seed")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ValueError(f"{source}: field 'seed' must be an integer or null, got {seed!r}")
        vehicles = data["vehicles"]
        if not isinstance(vehicles, list):
            raise ValueError(f"{source}: field 'vehicles' must be a list, got {type(vehicles).__name__}")
        if len(vehicles) > MAX_VEHICLES:
            raise ValueError(f"{source}: field 'vehicles' holds {len(vehicles)}, more than the {MAX_VEHICLES} accepted")
        cols: dict[str, list] = {k: [] for k in VEHICLE_FIELDS}
        for i, v in enumerate(vehicles):
            if not isinstance(v, dict):
                raise ValueError(f"{source}: vehicles[{i}] must be an object with fields {fields_}")
            for key in ("id", "time", "route", "speed"):
                if key not in v:
                    raise ValueError(f"{source}: vehicles[{i}] is missing field {key!r}")
            unknown = set(v) - set(fields_)
            if unknown:
                raise ValueError(
                    f"{source}: vehicles[{i}] has unknown fields {sorted(unknown)}; allowed (version {version}): "
                    f"{fields_}"
                )
            human = v.get("human", False)
            if not isinstance(human, bool):
                raise ValueError(f"{source}: vehicles[{i}].human must be true or false, got {human!r}")
            cols["human"].append(human)
            if isinstance(v["id"], bool) or not isinstance(v["id"], int) or not -(2**63) <= v["id"] < 2**63:
                raise ValueError(f"{source}: vehicles[{i}].id must be a 64-bit integer, got {v['id']!r}")
            if not isinstance(v["route"], str):
                raise ValueError(f"{source}: vehicles[{i}].route must be a string, got {v['route']!r}")
            for key, default in (("time", None), ("speed", None), ("length", 5.0), ("width", 2.0)):
                value = v.get(key, default)
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not _fits_float(value):
                    raise ValueError(f"{source}: vehicles[{i}].{key} must be a number, got {value!r}")
                cols[key].append(float(value))
            cols["id"].append(v["id"])
            cols["route"].append(v["route"])
        meta = data.get("meta") or {}
        if not isinstance(meta, dict):
            raise ValueError(f"{source}: field 'meta' must be an object, got {type(meta).__name__}")
        try:
            return cls(
                layout=data["layout"], duration=float(duration), seed=seed,
                vehicle_id=np.asarray(cols["id"], np.int64), time=cols["time"], route=tuple(cols["route"]),
                speed=cols["speed"], length=cols["length"], width=cols["width"], meta=meta,
                human=np.asarray(cols["human"], bool),
            )  # fmt: skip
        except ValueError as err:
            raise ValueError(str(err).replace("scenario:", f"{source}:", 1)) from None

    @classmethod
    def load(cls, path: str | Path) -> Scenario:
        """Read and validate a JSON scenario file.

        :param path: the file
        :raises ValueError: for a missing, unreadable or invalid file, naming the file and the field
        """
        from sb3_graph.files.safe_values import UnsafeValueError, read_regular_file

        path = Path(path)
        try:  # a FIFO or a device (also behind a link) is refused before it is opened, a huge file by size
            text = read_regular_file(path, "scenario file", MAX_FILE_BYTES).decode("utf-8")
        except UnsafeValueError as err:
            raise ValueError(str(err)) from None
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a text (UTF-8 JSON) scenario file") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(
                f"{path}: not valid JSON ({err.msg} at line {err.lineno}, column {err.colno})"
            ) from None
        except RecursionError:
            raise ValueError(f"{path}: not a scenario file (JSON nested too deeply)") from None
        return cls.from_dict(data, source=str(path))


def _fits_float(value: int | float) -> bool:
    """An int that a float can hold (JSON allows integers of any size)."""
    try:
        float(value)
    except OverflowError:
        return False
    return True


HUMAN_SHARE_ALLOWED = "a number in [0, 1] or a pair [low, high] with 0 <= low <= high <= 1"


def check_human_share(value: Any, name: str = "human_share") -> tuple[float, float]:
    """The share of human drivers as a range ``(low, high)`` (a number ``x`` gives ``(x, x)``).

    :param value: a number in [0, 1], or a pair ``[low, high]`` (a share drawn per episode or scenario)
    :param name: the name shown in the error
    :raises ValueError: naming ``name`` and the allowed values
    """
    import numbers

    def number(x: Any) -> bool:
        return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_)) and 0 <= x <= 1

    if number(value):
        return float(value), float(value)
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(number(x) for x in value) and value[0] <= value[1]:
        return float(value[0]), float(value[1])
    raise ValueError(f"{name} must be {HUMAN_SHARE_ALLOWED}, got {value!r}")


def human_rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    """The human drivers' own random stream for ``seed`` (a generator: a child of its seed sequence,
    which takes no draw from it)."""
    if isinstance(seed, np.random.Generator):
        return np.random.default_rng(seed.bit_generator.seed_seq.spawn(1)[0])
    return np.random.default_rng(None if seed is None else [HUMAN_STREAM, int(seed)])


def human_flags(
    count: int, share: Any, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """Which of ``count`` vehicles are human-driven.

    :param count: number of vehicles
    :param share: ``human_share`` (see :func:`check_human_share`); a range draws the share first
    :param rng: the human drivers' stream (:func:`human_rng`); a share of 0 takes no draw from it
    :return: ``(count,)`` bool flags and the share used
    """
    lo, hi = check_human_share(share)
    if hi == 0:
        return np.zeros(count, bool), 0.0
    value = float(rng.uniform(lo, hi)) if hi > lo else lo
    return rng.random(count) < value, value


def generate_scenario(
    layout: Layout | str,
    duration: float,
    rng: np.random.Generator | int,
    rate_range: tuple[float, float] = (0.2, 0.4),
    minor_factor: float = 0.5,
    min_headway: float = 1.0,
    speed_range: tuple[float, float] = (0.6, 1.0),
    length: float = 5.0,
    width: float = 2.0,
    human_share: float | tuple[float, float] = 0.0,
) -> Scenario:
    """Draw an evaluation scenario.

    One rate is drawn uniformly from ``rate_range`` [veh/s] for every major-road spawn lane; minor
    lanes get ``minor_factor`` times it. Inter-arrival times on a lane are shifted-exponential,
    ``min_headway + Exp(1 / rate - min_headway)``, so their mean is ``1 / rate`` and no two
    appearances on a lane are closer than ``min_headway``. Destinations are uniform over the lane's
    routes; speeds uniform in ``speed_range`` times the lane speed limit. Ids follow appearance time.

    :param layout: a layout or its name
    :param duration: scenario length [s]
    :param rng: random generator, or an integer seed (then recorded in the scenario)
    :param rate_range: ``(low, high)`` vehicle rate per major-road lane [veh/s]
    :param minor_factor: rate factor for minor-road lanes
    :param min_headway: the shift of the exponential distribution [s]
    :param speed_range: initial speed as fractions of the lane speed limit
    :param length: vehicle length [m]
    :param width: vehicle width [m]
    :param human_share: probability that a vehicle is human-driven, or a range ``[low, high]`` to draw
        it from; drawn with :func:`human_rng` of the seed (default 0: no draw, all automated)
    :return: the scenario; ``meta["human_share"]`` records the share when it is not 0
    """
    lay = named_layout(layout) if isinstance(layout, str) else layout
    seed = None
    humans = human_rng(rng) if check_human_share(human_share)[1] > 0 else None
    if not isinstance(rng, np.random.Generator):
        seed = int(rng)
        rng = np.random.default_rng(seed)
    lo, hi = (float(x) for x in rate_range)
    if not (0 < lo <= hi):
        raise ValueError(f"rate_range must satisfy 0 < low <= high, got {rate_range}")
    if not 0 < minor_factor:
        raise ValueError(f"minor_factor must be > 0, got {minor_factor}")
    if not (min_headway >= 0 and hi * max(1.0, minor_factor) * min_headway < 1):
        raise ValueError(
            f"min_headway must be >= 0 and shorter than the mean headway 1/rate, got {min_headway}"
        )
    if not (0 <= speed_range[0] <= speed_range[1]):
        raise ValueError(f"speed_range must satisfy 0 <= low <= high, got {speed_range}")
    if not duration > 0:
        raise ValueError(f"duration must be > 0, got {duration}")
    base = float(rng.uniform(lo, hi))
    times, routes, speeds = [], [], []
    # A loop over the few spawn lanes (not the hot path); arrivals are drawn vectorized.
    for k in range(len(lay.spawn_lanes)):
        rate = base * (1.0 if lay.spawn_priority[k] == 1 else minor_factor)
        count = int(duration * rate * 2 + 10)
        gaps = min_headway + rng.exponential(1.0 / rate - min_headway, count)
        gaps[0] = rng.exponential(1.0 / rate)  # the first arrival of a Poisson stream
        t = np.cumsum(gaps)
        t = t[t < duration]
        candidates = lay.spawn_routes(k)
        r = candidates[rng.integers(0, len(candidates), t.size)]
        limit = lay.speed_limit[r, 0]
        times.append(t)
        routes.append(r)
        speeds.append(rng.uniform(speed_range[0], speed_range[1], t.size) * limit)
    t_all = np.concatenate(times)
    order = np.argsort(t_all, kind="stable")
    r_all = np.concatenate(routes)[order]
    k_all = order.size
    meta = {"rate_major": base, "rate_minor": base * minor_factor, "min_headway": min_headway}
    human = np.zeros(k_all, bool)
    if humans is not None:
        human, meta["human_share"] = human_flags(k_all, human_share, humans)
    return Scenario(
        layout=lay.name, duration=float(duration), seed=seed,
        vehicle_id=np.arange(k_all), time=t_all[order], route=tuple(lay.route_names[i] for i in r_all),
        speed=np.concatenate(speeds)[order], length=np.full(k_all, length), width=np.full(k_all, width),
        meta=meta, human=human,
    )  # fmt: skip


def demand_scenario(
    layout: Layout | str,
    duration: float,
    rng: np.random.Generator | int,
    demand: float,
    human_share: float | tuple[float, float] = 0.0,
) -> Scenario:
    """Draw an evaluation scenario at a fixed demand (the demand sweep's generator).

    :func:`generate_scenario` with the rate fixed to ``demand`` per major-road lane and half of it
    per minor-road lane (as in the paper): Poisson arrivals with the minimum headway, the same
    destinations and initial speeds.

    :param layout: a layout or its name
    :param duration: scenario length [s]
    :param rng: random generator, or an integer seed
    :param demand: arrivals per second and major-road lane, in ``(0, 1)`` (the 1 s minimum headway)
    :param human_share: share of human drivers (see :func:`generate_scenario`)
    :return: the scenario; ``meta["demand"]`` records ``demand``
    """
    demand = float(demand)
    if not 0 < demand < 1:
        raise ValueError(f"demand must be in (0, 1) veh/s per major-road lane (1 s minimum headway), got {demand}")
    scenario = generate_scenario(layout, duration, rng, rate_range=(demand, demand), human_share=human_share)
    scenario.meta["demand"] = demand
    return scenario


class TrainingTraffic:
    """Random spawns for training.

    :param layout: the intersection
    :param spawn_probability: probability per spawn lane and policy step
    :param speed_range: initial speed as fractions of the lane speed limit
    :param length: vehicle length [m]
    :param width: vehicle width [m]
    :param min_gap: smallest bumper gap to the vehicle ahead at spawning [m]
    :param queue: largest number of vehicles that wait per spawn lane when their spawn point is not
        free (0: a blocked spawn is dropped, as before). Waiting vehicles appear once there is
        space, and count in :attr:`waiting`, so that a reward can charge the delay of a planner
        that keeps the entry blocked (evaluation scenarios queue in the same way).
    """

    def __init__(
        self,
        layout: Layout,
        spawn_probability: float = 0.05,
        speed_range: tuple[float, float] = (0.6, 1.0),
        length: float = 5.0,
        width: float = 2.0,
        min_gap: float = 5.0,
        queue: int = 0,
    ) -> None:
        self.layout = layout
        self.queue_limit = int(queue)
        self.queue = np.zeros(len(layout.spawn_lanes), np.int64)
        self.spawn_probability = float(spawn_probability)
        self.speed_range = speed_range
        self.length = float(length)
        self.width = float(width)
        self.min_gap = float(min_gap)
        self.next_id = 0
        # Mixed traffic: each spawn is human-driven with this probability, drawn from ``human_rng``
        # (the environment sets both per episode; 0 draws nothing).
        self.human_share = 0.0
        self.human_rng: np.random.Generator | None = None
        # Routes grouped by spawn lane, for drawing one destination per lane in one gather.
        num_lanes = len(layout.spawn_lanes)
        self._counts = np.bincount(layout.route_spawn_lane, minlength=num_lanes)
        self._first = np.concatenate([[0], np.cumsum(self._counts)[:-1]])
        self._by_lane = np.argsort(layout.route_spawn_lane, kind="stable")

    def reset(self) -> None:
        self.next_id = 0
        self.queue[:] = 0

    @property
    def waiting(self) -> int:
        """Vehicles waiting for space at their spawn points."""
        return int(self.queue.sum())

    def spawn(
        self, sim: Simulation, rng: np.random.Generator, probability: float | None = None
    ) -> np.ndarray:
        """Let vehicles appear at the current time.

        The same number of random draws is taken every call, so runs are reproducible.

        :param sim: the simulation to add vehicles to
        :param rng: random generator
        :param probability: overrides ``spawn_probability`` for this call (e.g. 1 at reset)
        :return: ids of the new vehicles
        """
        lay = self.layout
        num_lanes = len(lay.spawn_lanes)
        p = self.spawn_probability if probability is None else probability
        draw = rng.random(num_lanes) < p
        pick = rng.random(num_lanes)
        frac = rng.uniform(self.speed_range[0], self.speed_range[1], num_lanes)
        counts = self._counts
        route = self._by_lane[self._first + np.minimum((pick * counts).astype(np.int64), counts - 1)]
        speed = frac * lay.speed_limit[route, 0]
        human = None
        if self.human_share > 0:  # the same number of draws every call, from the human stream
            human = self.human_rng.random(num_lanes) < self.human_share
        if self.queue_limit:
            self.queue = np.minimum(self.queue + draw, self.queue_limit)
            draw = self.queue > 0
        lanes = np.flatnonzero(draw)
        if lanes.size == 0:
            return np.zeros(0, np.int64)
        free = sim.spawn_free(lanes, speed[lanes], np.full(lanes.size, self.length), self.min_gap)
        lanes = lanes[free][: max(sim.max_vehicles - sim.num_vehicles, 0)]
        if self.queue_limit:
            self.queue[lanes] -= 1
        ids = np.arange(self.next_id, self.next_id + lanes.size, dtype=np.int64)
        self.next_id += lanes.size
        if lanes.size:
            sim.add(
                route[lanes], speed[lanes], ids, self.length, self.width, human=None if human is None else human[lanes]
            )
        return ids


class ScenarioTraffic:
    """Replays a :class:`Scenario`: appearances in time order per spawn lane, waiting while not free.

    :param layout: the intersection (must match ``scenario.layout``)
    :param scenario: the scenario
    :param min_gap: smallest bumper gap to the vehicle ahead at spawning [m]
    """

    def __init__(self, layout: Layout, scenario: Scenario, min_gap: float = 5.0) -> None:
        if scenario.layout != layout.name:
            raise ValueError(
                f"scenario is for layout {scenario.layout!r}, the environment uses {layout.name!r}"
            )
        self.layout = layout
        self.scenario = scenario
        self.min_gap = float(min_gap)
        route = np.array([layout.route_id(r) for r in scenario.route], np.int64)
        lane = layout.route_spawn_lane[route]
        order = np.lexsort((scenario.vehicle_id, scenario.time, lane))  # by lane, then time, then id
        self.route = route[order]
        self.lane = lane[order]
        self.time = scenario.time[order]
        self.speed = scenario.speed[order]
        self.length = scenario.length[order]
        self.width = scenario.width[order]
        self.vehicle_id = scenario.vehicle_id[order]
        self.human = scenario.human[order]
        num_lanes = len(layout.spawn_lanes)
        self.lane_begin = np.searchsorted(self.lane, np.arange(num_lanes))
        self.lane_end = np.searchsorted(self.lane, np.arange(num_lanes), side="right")
        self.reset()

    def reset(self) -> None:
        self.cursor = self.lane_begin.copy()
        self.waiting = 0

    def spawn(
        self, sim: Simulation, rng: np.random.Generator | None = None, probability: float | None = None
    ) -> np.ndarray:
        """Let the due appearances that fit appear (at most one per lane); return their ids."""
        del rng, probability  # replay is deterministic
        has = self.cursor < self.lane_end
        head = np.minimum(self.cursor, len(self.time) - 1) if len(self.time) else self.cursor
        due = has & (self.time[head] <= sim.time + 1e-9) if len(self.time) else has
        lanes = np.flatnonzero(due)
        new_ids = np.zeros(0, np.int64)
        if lanes.size:
            rows = self.cursor[lanes]
            free = sim.spawn_free(lanes, self.speed[rows], self.length[rows], self.min_gap)
            rows = rows[free][: max(sim.max_vehicles - sim.num_vehicles, 0)]
            if rows.size:
                sim.add(
                    self.route[rows],
                    self.speed[rows],
                    self.vehicle_id[rows],
                    self.length[rows],
                    self.width[rows],
                    human=self.human[rows],
                )
                self.cursor[self.lane[rows]] += 1
                new_ids = self.vehicle_id[rows]
        # Appearances whose time has come but that are still waiting for space.
        # (A loop over the few spawn lanes; each lane's times are sorted.)
        due_counts = np.array(
            [
                np.searchsorted(self.time[b:e], sim.time + 1e-9, side="right")
                for b, e in zip(self.cursor, self.lane_end)
            ]
        )
        self.waiting = int(due_counts.sum())
        return new_ids
