"""The faults a shield is declared to tolerate (:class:`ShieldBounds`), how the command line names them
(``--shield-bounds``) and which faults of an environment lie beyond them (:func:`exceeded`).

The bounds are a promise about the perceived scene (:mod:`envs.simulation.perception`) that the shield may rely on:
every vehicle's perceived position along its path is within ``position`` of the truth and its speed within
``speed``, no state is older than ``age``, a command applies at most ``latency`` late and the realised acceleration
follows it with a first-order lag of at most ``lag``. All zero (the default) is the exact world. The environment's
``faults`` setting (:mod:`envs.simulation.faults`) says what the world does; a run whose faults reach beyond the
bounds is warned about at its start, and the vehicle-steps beyond them are counted (``fault_excursions``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.simulation.faults import fault_config, faults_active

_MAX_ERROR = 1e3  # [m] or [m/s], as the fault model's checks
_MAX_TIME = 3600.0  # [s]
# Every bound with its unit and largest value.
BOUND_RULES: dict[str, tuple[str, float]] = {
    "position": ("m", _MAX_ERROR),
    "speed": ("m/s", _MAX_ERROR),
    "age": ("s", _MAX_TIME),
    "latency": ("s", _MAX_TIME),
    "lag": ("s", _MAX_TIME),
}
# Rounding allowance when a fault is compared with its bound.
_TOLERANCE = 1e-9


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class ShieldBounds:
    """The faults a shield keeps its guarantee within (all zero: the exact world).

    :param position: largest error of a perceived position along the path [m]
    :param speed: largest error of a perceived speed [m/s]
    :param age: age of the oldest state the scene may hold (the latency, plus the time a state is held while
        messages are lost) [s]
    :param latency: how much later than planned a command applies at most [s]
    :param lag: largest time constant of the first-order lag between a command and the realised acceleration [s]
    """

    position: float = 0.0
    speed: float = 0.0
    age: float = 0.0
    latency: float = 0.0
    lag: float = 0.0

    def __post_init__(self) -> None:
        for key, (unit, high) in BOUND_RULES.items():
            value = getattr(self, key)
            if not _number(value) or not 0.0 <= float(value) <= high:
                raise ValueError(f"shield bound {key!r} must be a number in [0, {high:g}] [{unit}], got {value!r}")
            object.__setattr__(self, key, float(value))

    @property
    def exact(self) -> bool:
        """Whether these are the bounds of the exact world (every bound zero)."""
        return not any(getattr(self, key) for key in BOUND_RULES)

    def text(self) -> str:
        """``"none"`` or ``"position=3,speed=1,..."``, what :func:`parse_shield_bounds` reads back."""
        if self.exact:
            return "none"
        return ",".join(f"{key}={getattr(self, key):g}" for key in BOUND_RULES)


#: The bounds of the imperfect world that the shield is built to hold within: position error bounded at 3 m, speed
#: error at 1 m/s, a state held at most 1 s, 100 ms latency, 0.3 s actuation lag.
DECLARED_BOUNDS = ShieldBounds(position=3.0, speed=1.0, age=1.0, latency=0.1, lag=0.3)

SHIELD_BOUNDS_HELP = (
    "'none' (the exact world), 'declared' (position=3,speed=1,age=1,latency=0.1,lag=0.3) or KEY=VALUE,... with "
    f"keys {list(BOUND_RULES)} (m, m/s, s, s, s; unnamed keys 0; 'declared,lag=0.5' starts from the declared ones)"
)


def parse_shield_bounds(text: str | None) -> ShieldBounds:
    """The bounds a command-line word names.

    :param text: ``"none"``, ``"declared"``, or ``"key=value,..."`` (optionally after ``"declared,"`` or
        ``"none,"``); ``None``: none
    :return: the bounds
    :raises ValueError: one line naming the key and its allowed range
    """
    if text is None:
        return ShieldBounds()
    parts = [part.strip() for part in str(text).split(",")]
    base: dict[str, float] = {}
    if parts and parts[0].lower() in ("none", "declared"):
        base = dataclasses.asdict(DECLARED_BOUNDS) if parts[0].lower() == "declared" else {}
        parts = parts[1:]
    elif not parts or parts == [""]:
        raise ValueError(f"--shield-bounds: empty; expected {SHIELD_BOUNDS_HELP}")
    for part in parts:
        key, sep, value = part.partition("=")
        key = key.strip().lower()
        if not sep:
            raise ValueError(f"--shield-bounds: {part!r} is not KEY=VALUE; expected {SHIELD_BOUNDS_HELP}")
        if key not in BOUND_RULES:
            raise ValueError(f"--shield-bounds: unknown key {key!r}; allowed keys {list(BOUND_RULES)}")
        unit, high = BOUND_RULES[key]
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number) or not 0.0 <= number <= high:
            raise ValueError(f"--shield-bounds: {key!r} must be a number in [0, {high:g}] [{unit}], got {value!r}")
        base[key] = number
    return ShieldBounds(**base)


def fault_reach(faults: dict[str, Any] | None) -> dict[str, float]:
    """How far each fault of a ``faults`` setting can reach, in the terms of :class:`ShieldBounds`.

    :param faults: the environment's ``faults`` (checked or not; ``None`` or ``{}``: none)
    :return: ``{bound key: largest value}``; an unbounded error with a standard deviation > 0 reaches ``inf``
    """
    f = fault_config(faults)
    if not faults_active(f):
        return dict.fromkeys(BOUND_RULES, 0.0)

    def error(sigma: float, bound: float | None) -> float:
        return 0.0 if sigma == 0 else (math.inf if bound is None else bound)

    oldest = max(f["latency"], f["max_age"]) if f["loss"] > 0 else f["latency"]
    return {
        "position": error(f["position_sigma"], f["position_bound"]),
        "speed": error(f["speed_sigma"], f["speed_bound"]),
        "age": oldest,
        "latency": f["latency"],
        "lag": f["lag"],
    }


def exceeded(bounds: ShieldBounds | None, faults: dict[str, Any] | None) -> list[str]:
    """Which faults of an environment exceed a shield's declared bounds, one short phrase each.

    :param bounds: the shield's bounds (``None``: the exact world)
    :param faults: the environment's ``faults`` setting
    :return: e.g. ``["position error up to 3 m > 0 m", "lag 0.3 s > 0 s"]``; empty when the bounds hold
    """
    bounds = bounds or ShieldBounds()
    names = {"position": "position error", "speed": "speed error", "age": "state age"}
    out = []
    for key, reach in fault_reach(faults).items():
        declared = getattr(bounds, key)
        if reach > declared + _TOLERANCE:
            unit = BOUND_RULES[key][0]
            value = "unbounded" if math.isinf(reach) else f"up to {reach:g} {unit}"
            out.append(f"{names.get(key, key)} {value} > {declared:g} {unit}")
    return out


def bounds_warning(bounds: ShieldBounds | None, faults: dict[str, Any] | None) -> str | None:
    """The one-line warning at the start of a run whose faults exceed the shield's bounds, or ``None``.

    :param bounds: the shield's bounds (``None``: the exact world)
    :param faults: the environment's ``faults`` setting
    """
    beyond = exceeded(bounds, faults)
    if not beyond:
        return None
    declared = (bounds or ShieldBounds()).text()
    return (
        f"warning: the environment's faults exceed the shield's declared bounds (--shield-bounds {declared}): "
        f"{'; '.join(beyond)}; the shield's guarantee does not cover them (the vehicle-steps beyond are counted "
        f"as fault_excursions)"
    )


#: The run columns of :func:`excursions`: vehicle-steps beyond the bounds, in all and per kind.
EXCURSION_COLUMNS = ("fault_excursions", "excursions_position", "excursions_speed", "excursions_age")


def excursions(errors: tuple[np.ndarray, np.ndarray, np.ndarray] | None, bounds: ShieldBounds | None) -> np.ndarray:
    """Vehicle-steps of one perceived scene that rest on a measurement beyond the declared bounds: a position or
    speed error larger than the bound, or a state older than the age bound. (These are the faults the world made; a
    tracker's estimate built from them is not judged here.)

    :param errors: the true errors of the scene's measurements per row: arcs [m], speeds [m/s] and ages [s]
        (:meth:`envs.simulation.env.CoopIntersectionEnv.perception_errors`); ``None``: an exact scene
    :param bounds: the declared bounds (``None``: the exact world, where any error is an excursion)
    :return: ``(4,)`` counts in the order of :data:`EXCURSION_COLUMNS`: vehicles beyond any bound, beyond the
        position bound, the speed bound, the age bound
    """
    if errors is None:
        return np.zeros(4, np.int64)
    bounds = bounds or ShieldBounds()
    arc, speed, age = (np.asarray(x, float) for x in errors)
    beyond = np.stack([
        np.abs(arc) > bounds.position + _TOLERANCE,
        np.abs(speed) > bounds.speed + _TOLERANCE,
        age > bounds.age + _TOLERANCE,
    ])  # fmt: skip
    return np.concatenate([[beyond.any(axis=0).sum()], beyond.sum(axis=1)]).astype(np.int64)
