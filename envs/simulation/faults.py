"""The fault model of an imperfect world: its settings (the environment's ``faults`` key), the random draws that
every fault takes, and the actuator (latency and lag between a command and the acceleration it realises).

What is perceived (perception error, message loss, the scene's age) is built from these draws in
:mod:`envs.simulation.perception`; the truth stays in the plant. The faults:

- ``position_sigma`` [m], ``position_bound`` [m], ``position_tau`` [s]: each vehicle's position along its path is off
  by a stationary Gauss-Markov (Ornstein-Uhlenbeck) error of standard deviation ``position_sigma`` and correlation time
  ``position_tau`` (0: a fresh error every message), clipped at ``+-position_bound`` (``null``: not clipped);
- ``speed_sigma`` [m/s], ``speed_bound`` [m/s], ``speed_tau`` [s]: the same for its speed (a measured speed is never
  negative);
- ``loss``: the probability that a vehicle's message of a policy step is lost; its last state is held (and ages) until
  a message arrives. A state is never held longer than ``max_age`` [s]: the message that would make it older gets
  through (so ``max_age`` is a bound that a shield can declare). A vehicle's first message is never lost;
- ``latency`` [s], at most one policy period: the scene is this old when the planner receives it (each vehicle's
  state is the truth of ``latency`` seconds ago, read off the plant's sub-step trajectory), and each command applies
  this much later: the previous command holds for the first ``latency`` seconds of the period (a sub-step that the
  switch splits gets the time-weighted mean of the two);
- ``lag`` [s]: the realised acceleration follows the (delayed) command with a first-order lag of this time constant,
  integrated exactly over each sub-step (the sub-step applies its mean acceleration);
- ``tracker``: the planners see a per-vehicle tracker's estimate (:mod:`envs.simulation.tracker`) instead of the raw
  (held, aged) measurements; ``process_noise`` [m/s^2]: the tracker's white-acceleration noise.

Every draw is a pure function of the episode's fault seed, the vehicle's id, the policy step and the stream (a
counter-based generator: SplitMix64 over the key, then Box-Muller): the same vehicle gets the same errors at the same
step under every planner, whatever else is in the scene, so runs are reproducible and paired.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np

# Every fault setting with its default: no fault at all (the perceived scene is the true one, the same arrays).
FAULT_DEFAULTS: dict[str, Any] = {
    "position_sigma": 0.0,
    "position_bound": None,
    "position_tau": 1.0,
    "speed_sigma": 0.0,
    "speed_bound": None,
    "speed_tau": 0.0,
    "loss": 0.0,
    "max_age": 1.0,
    "latency": 0.0,
    "lag": 0.0,
    "tracker": True,
    "process_noise": 1.0,
}
# The keys whose non-zero value makes the world imperfect.
FAULT_KEYS = ("position_sigma", "speed_sigma", "loss", "latency", "lag")
# Upper bounds far above any real fault: a typo such as sigma 1e9 fails at once.
_MAX_ERROR = 1e3  # [m] or [m/s]
_MAX_TIME = 3600.0  # [s]

_NUMBER_RULES: dict[str, tuple[float, float, bool, str]] = {  # key -> (low, high, low excluded, unit)
    "position_sigma": (0.0, _MAX_ERROR, False, "m"),
    "position_bound": (0.0, _MAX_ERROR, True, "m"),
    "position_tau": (0.0, _MAX_TIME, False, "s"),
    "speed_sigma": (0.0, _MAX_ERROR, False, "m/s"),
    "speed_bound": (0.0, _MAX_ERROR, True, "m/s"),
    "speed_tau": (0.0, _MAX_TIME, False, "s"),
    "loss": (0.0, 1.0, False, ""),
    "max_age": (0.0, _MAX_TIME, True, "s"),
    "latency": (0.0, _MAX_TIME, False, "s"),
    "lag": (0.0, _MAX_TIME, False, "s"),
    "process_noise": (0.0, 1e3, True, "m/s^2"),
}
FAULTS_ALLOWED = (
    f"a dict with some of the keys {list(FAULT_DEFAULTS)} (errors, times and probabilities >= 0, loss in [0, 1], "
    f"bounds > 0 or null, latency at most one policy period, tracker true or false)"
)


def _allowed(key: str) -> str:
    low, high, strict, unit = _NUMBER_RULES[key]
    text = f"a number in {'(' if strict else '['}{low:g}, {high:g}]" + (f" [{unit}]" if unit else "")
    return text + (" or null (no bound)" if key.endswith("_bound") else "")


def _number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def fault_config(value: Any, policy_period: float | None = None) -> dict[str, Any]:
    """The ``faults`` setting checked and with its defaults filled in.

    :param value: the user's ``faults`` dict (a subset of :data:`FAULT_DEFAULTS`) or ``None`` (no faults)
    :param policy_period: the policy period [s], the largest ``latency`` (unchecked when ``None``)
    :return: a new dict with every key of :data:`FAULT_DEFAULTS` (an infinite bound stored as ``None``)
    :raises ValueError: one line naming the entry and its allowed values
    """
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise ValueError(f"config key 'faults' must be {FAULTS_ALLOWED}, got {value!r}")
    unknown = sorted(set(value) - set(FAULT_DEFAULTS))
    if unknown:
        raise ValueError(f"config key 'faults': unknown entries {unknown}; allowed: {list(FAULT_DEFAULTS)}")
    merged = {**FAULT_DEFAULTS, **value}
    for key, rule in _NUMBER_RULES.items():
        x = merged[key]
        if key.endswith("_bound") and (x is None or (_number(x) and x == math.inf)):
            merged[key] = None
            continue
        low, high, strict, _ = rule
        if not _number(x) or not math.isfinite(x) or x < low or x > high or (strict and x == low):
            raise ValueError(f"config key 'faults' entry {key!r} must be {_allowed(key)}, got {x!r}")
        merged[key] = float(x)
    if not isinstance(merged["tracker"], (bool, np.bool_)):
        raise ValueError(f"config key 'faults' entry 'tracker' must be true or false, got {merged['tracker']!r}")
    merged["tracker"] = bool(merged["tracker"])
    if policy_period is not None and merged["latency"] > policy_period + 1e-12:
        raise ValueError(
            f"config key 'faults' entry 'latency' must be a number in [0, {policy_period:g}] [s] (at most one policy "
            f"period), got {merged['latency']!r}"
        )
    return merged


def faults_active(faults: dict[str, Any] | None) -> bool:
    """Whether a checked ``faults`` setting makes the world imperfect (otherwise nothing is drawn or changed)."""
    return bool(faults) and any(faults[key] > 0 for key in FAULT_KEYS)


# ---------------------------------------------------------------------- draws
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
# Streams of draws per vehicle and step.
POSITION, SPEED, LOSS = 0, 2, 4


def _mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser (uint64 arithmetic wraps)."""
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


class FaultDraws:
    """Counter-based random draws: one value per (seed, vehicle id, step, stream), vectorized over vehicles.

    :param seed: the episode's fault seed
    """

    def __init__(self, seed: int) -> None:
        self.seed = int(seed) % (1 << 64)

    def uniform(self, ids: np.ndarray, step: int, stream: int) -> np.ndarray:
        """``(n,)`` uniform draws in (0, 1) for these vehicle ids at this step."""
        with np.errstate(over="ignore"):
            key = _mix(np.full(1, self.seed, np.uint64) + _GOLDEN)
            key = _mix(key ^ (np.uint64(step % (1 << 62)) * _GOLDEN + np.uint64(stream)))
            bits = _mix(key ^ (np.asarray(ids, np.int64).astype(np.uint64) * _M2))
        return ((bits >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)

    def normal(self, ids: np.ndarray, step: int, stream: int) -> np.ndarray:
        """``(n,)`` standard normal draws (Box-Muller over streams ``stream`` and ``stream + 1``)."""
        u1 = self.uniform(ids, step, stream)
        u2 = self.uniform(ids, step, stream + 1)
        return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


class ById:
    """Per-vehicle values kept across steps, keyed by vehicle id (vehicles appear and leave; rows reorder)."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.columns: dict[str, np.ndarray] = {}

    def find(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each id's values are: ``(n,)`` positions into the stored rows and ``(n,)`` bool found."""
        ids = np.asarray(ids, np.int64)
        if self.ids.size == 0:
            return np.zeros(ids.size, np.int64), np.zeros(ids.size, bool)
        order = np.argsort(self.ids, kind="stable")
        pos = np.minimum(np.searchsorted(self.ids[order], ids), self.ids.size - 1)
        rows = order[pos]
        return rows, self.ids[rows] == ids

    def get(self, name: str, rows: np.ndarray, found: np.ndarray, default: np.ndarray | float) -> np.ndarray:
        """The stored column ``name`` at ``rows`` where found, ``default`` elsewhere."""
        column = self.columns.get(name)
        if column is None or column.size == 0:
            return np.broadcast_to(np.asarray(default, float), found.shape).astype(float)
        return np.where(found, column[rows] if rows.size else np.zeros(0), default)

    def store(self, ids: np.ndarray, **columns: np.ndarray) -> None:
        """Replace everything by these vehicles' values (the vehicles gone are forgotten)."""
        self.ids = np.asarray(ids, np.int64).copy()
        self.columns = {k: np.asarray(v, float).copy() for k, v in columns.items()}


# ---------------------------------------------------------------------- actuation
class Actuator:
    """Latency and lag between a command and the acceleration that a vehicle realises, per sub-step.

    A plant calls it with the commanded accelerations of a policy period and integrates what it returns
    (:attr:`envs.simulation.engine.Simulation.actuator`).

    :param latency: the command applies this much later [s] (the previous command holds until then)
    :param lag: time constant of the first-order lag of the realised acceleration [s] (0: none)
    :param substeps: sub-steps per policy period
    :param h: sub-step length [s]
    """

    def __init__(self, latency: float, lag: float, substeps: int, h: float) -> None:
        self.substeps = int(substeps)
        self.h = float(h)
        start = np.arange(self.substeps) * self.h
        # Share of each sub-step under the previous command (latency up to one period).
        self.old_share = np.clip((float(latency) - start) / self.h, 0.0, 1.0)[:, None]
        # Over a sub-step with the command c held, r(t) = c + (r0 - c) exp(-t / lag): the state decays by `decay`,
        # and the sub-step's mean acceleration (what its speed change needs) is c + (r0 - c) * `mean_share`.
        self.decay = math.exp(-self.h / lag) if lag > 0 else 0.0
        self.mean_share = lag / self.h * (1.0 - self.decay) if lag > 0 else 0.0
        self.memory = ById()
        self.last_commanded = np.zeros((self.substeps, 0))

    def reset(self) -> None:
        """Forget every vehicle (a new episode)."""
        self.memory = ById()
        self.last_commanded = np.zeros((self.substeps, 0))

    def __call__(self, vehicle_id: np.ndarray, command: np.ndarray, speed: np.ndarray | None = None) -> np.ndarray:
        """The realised accelerations of each sub-step of the coming period.

        :param vehicle_id: ``(n,)`` ids of the rows
        :param command: ``(n,)`` commanded accelerations, already within the bounds [m/s^2]
        :param speed: ``(n,)`` speeds now [m/s]: a vehicle at rest is not decelerating (its brakes hold it), so its
            realised acceleration starts from no less than 0
        :return: ``(S, n)`` mean accelerations over each sub-step (exact for its speed change); a vehicle seen for the
            first time had command 0 and realised 0 before
        """
        rows, found = self.memory.find(vehicle_id)
        previous = self.memory.get("command", rows, found, 0.0)
        realised = self.memory.get("realised", rows, found, 0.0)
        if speed is not None:
            realised = np.where(speed <= 0.0, np.maximum(realised, 0.0), realised)
        commanded = self.old_share * previous[None, :] + (1.0 - self.old_share) * command[None, :]  # (S, n)
        out = np.empty_like(commanded)
        for k in range(self.substeps):  # a loop over time (3 sub-steps), vectorized over vehicles
            out[k] = commanded[k] + (realised - commanded[k]) * self.mean_share
            realised = commanded[k] + (realised - commanded[k]) * self.decay
        self.memory.store(vehicle_id, command=command, realised=realised)
        self.last_commanded = commanded
        return out
