"""Validation of the intersection environments' ``default_config()`` dictionaries.

Every key of the configuration has a rule: its type and the values it allows. An unknown key, a
wrong type or an impossible value raises a ``ValueError`` that names the key and what is allowed.
NumPy numbers count as numbers (and are stored as Python ones); sizes have upper bounds, so that a
typo such as ``max_vehicles=10**9`` fails at once instead of asking for gigabytes later.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.simulation.faults import FAULTS_ALLOWED, fault_config
from envs.simulation.graph import EDGE_FEATURES, VERTEX_FEATURES
from envs.simulation.plant import PLANTS
from envs.simulation.rewards import REWARD_PRESETS, REWARD_TERMS, preset_weights
from envs.simulation.sumo_junction import LAYOUT_HELP, NET_PREFIX, is_layout_name, named_layout
from envs.simulation.sumo_plant import libsumo_module
from envs.simulation.traffic import HUMAN_SHARE_ALLOWED, check_human_share

# What a collision does: "terminate" ends the episode (training, as in the paper); "remove" takes
# the vehicles involved out of the scene and goes on (evaluation: collision rate over a whole run).
COLLISION_HANDLING = ("terminate", "remove")
# Upper bounds of the physical quantities, far above any real vehicle: beyond them the rewards and
# the simulation overflow (an acceleration of 1e308 gives rewards of -inf).
MAX_DURATION = 86_400.0  # [s]
MAX_ACCELERATION = 100.0  # [m/s^2], about 10 g
MAX_SPEED = 100.0  # [m/s]
MAX_VEHICLE_SIZE = 30.0  # [m]
# Upper bounds of the observation's scales: the features (float32) stay finite, and far from its limit, for any
# path (s_ref [m], s_scale [1/m]: s times s_scale; d_max: the clip of the inverse distance feature).
MAX_S_REF = 1e4
MAX_S_SCALE = 1e3
MAX_D_MAX = 1e6
# Upper bounds of the sizes (vertices, edges, simulation sub-steps): far above any real scene.
MAX_VEHICLES = 1024
MAX_EDGES = 1 << 18
MAX_SIMULATION_FREQUENCY = 1000
# Base planners of a residual policy (``residual_base``): the policy's action corrects their command.
RESIDUAL_BASES = ("fullthrottle", "aim", "fifo", "pr", "glide")
# What the action means (``action``'s ``type``, highway-env's convention): one acceleration per
# vehicle, or one score per vehicle over glide's scheduler: a shift of its arrival order
# (``"priority"``) or of the distance from its line within which it follows its slot (``"advice"``).
ACTION_TYPES = ("acceleration", "priority", "advice")
SCHEDULER_ACTION_TYPES = ACTION_TYPES[1:]
# A priority score of +-1 shifts a vehicle's arrival key by this many seconds (``action``'s ``scale``).
DEFAULT_PRIORITY_SCALE = 5.0
# An advice score of +-1 moves a vehicle's advice window by this many metres (``action``'s ``scale``):
# +1 advises it from 80 m, the 4-way's whole approach.
DEFAULT_ADVICE_SCALE = 64.0
# Glide's parameter sets (``action``'s ``glide``, envs.planners.glide.GLIDE_VERSIONS): the first-phase control
# tuned for behind the shield (default), glide as first shipped (IDM following and AIM's zone guard), or the
# first hand-set recipe over the first-phase control (the one that lookahead searches over).
GLIDE_VERSION_NAMES = ("first_phase", "guarded", "recipe")
# (An acceleration action ignores its scale; it keeps the priority default, as before advice existed.)
DEFAULT_ACTION_SCALES = {
    "acceleration": DEFAULT_PRIORITY_SCALE,
    "priority": DEFAULT_PRIORITY_SCALE,
    "advice": DEFAULT_ADVICE_SCALE,
}
MAX_PRIORITY_SCALE = 3600.0


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_))


def _is_number(x: Any) -> bool:
    if not isinstance(x, numbers.Real) or isinstance(x, (bool, np.bool_)):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:  # an int beyond float range (JSON integers have no size limit)
        return False


@dataclass(frozen=True)
class Rule:
    """How one configuration key is checked.

    :param check: returns ``True`` for an allowed value
    :param allowed: human-readable description of the allowed values
    """

    check: Callable[[Any], bool]
    allowed: str


def _int(minimum: int, maximum: int | None = None) -> Rule:
    if maximum is None:
        return Rule(lambda x: _is_int(x) and x >= minimum, f"an integer >= {minimum}")
    return Rule(lambda x: _is_int(x) and minimum <= x <= maximum, f"an integer in [{minimum}, {maximum:,}]")


def _positive(maximum: float | None = None) -> Rule:
    if maximum is None:
        return Rule(lambda x: _is_number(x) and x > 0, "a number > 0")
    return Rule(lambda x: _is_number(x) and 0 < x <= maximum, f"a number in (0, {maximum:g}]")


def _non_negative() -> Rule:
    return Rule(lambda x: _is_number(x) and x >= 0, "a number >= 0")


def _probability() -> Rule:
    return Rule(lambda x: _is_number(x) and 0 <= x <= 1, "a number in [0, 1]")


def _bool() -> Rule:
    return Rule(lambda x: isinstance(x, (bool, np.bool_)), "true or false")


def _range(lower: float, strict: bool) -> Rule:
    def check(x: Any) -> bool:
        return (
            isinstance(x, (list, tuple))
            and len(x) == 2
            and all(_is_number(v) for v in x)
            and x[0] >= lower
            and (x[0] < x[1] if strict else x[0] <= x[1])
        )

    rel = "<" if strict else "<="
    return Rule(check, f"a pair [low, high] of numbers with {lower} <= low {rel} high")


# Largest reward weight (in magnitude): a sum of weighted terms must stay finite.
MAX_REWARD_WEIGHT = 1e6


def _weights(x: Any) -> bool:
    return (
        isinstance(x, dict)
        and set(x) <= set(REWARD_TERMS)
        and all(_is_number(v) and abs(v) <= MAX_REWARD_WEIGHT for v in x.values())
    )


def _action(x: Any) -> bool:
    return (
        isinstance(x, dict)
        and set(x) <= {"type", "scale", "glide", "hold"}
        and x.get("type", ACTION_TYPES[0]) in ACTION_TYPES
        and isinstance(x.get("hold", True), bool)
        and x.get("glide", GLIDE_VERSION_NAMES[0]) in GLIDE_VERSION_NAMES
        and ("scale" not in x or (_is_number(x["scale"]) and 0 < x["scale"] <= MAX_PRIORITY_SCALE))
    )


def action_config(value: dict[str, Any] | None) -> dict[str, Any]:
    """The ``action`` setting with its defaults filled in (``type``, ``scale``, ``glide`` and ``hold``).

    :param value: a checked ``action`` setting, or ``None`` (accelerations)
    """
    value = dict(value or {})
    kind = value.get("type", ACTION_TYPES[0])
    scale = float(value.get("scale", DEFAULT_ACTION_SCALES[kind]))
    glide = value.get("glide", GLIDE_VERSION_NAMES[0])
    return {"type": kind, "scale": scale, "glide": glide, "hold": value.get("hold", True)}


def _human_share(x: Any) -> bool:
    try:
        check_human_share(x)
    except ValueError:
        return False
    return True


def _distinct_names(allowed) -> Rule:
    """A list of distinct names from ``allowed`` (feature lists)."""
    return Rule(
        lambda x: isinstance(x, (list, tuple))
        and all(isinstance(v, str) for v in x)
        and set(x) <= set(allowed)
        and len(set(x)) == len(x),
        f"a list of distinct names from {list(allowed)}",
    )


RULES: dict[str, Rule] = {
    "layout": Rule(is_layout_name, LAYOUT_HELP),
    "plant": Rule(lambda x: isinstance(x, str) and x in PLANTS, f"one of {PLANTS}"),
    "simulation_frequency": _int(1, MAX_SIMULATION_FREQUENCY),
    "policy_frequency": _int(1, MAX_SIMULATION_FREQUENCY),
    "duration": _positive(MAX_DURATION),
    "max_vehicles": _int(1, MAX_VEHICLES),
    "max_edges": _int(0, MAX_EDGES),
    "edge_features": _distinct_names(EDGE_FEATURES),
    "vertex_features": _distinct_names(VERTEX_FEATURES),
    "spawn_probability": _probability(),
    "initial_spawn_probability": _probability(),
    "spawn_probability_range": Rule(
        lambda x: x is None or (_range(0.0, strict=False).check(x) and x[1] <= 1),
        "null or a pair [low, high] of probabilities with 0 <= low <= high <= 1",
    ),
    "initial_speed_range": _range(0.0, strict=True),
    "max_acceleration": _positive(MAX_ACCELERATION),
    "max_speed": _positive(MAX_SPEED),
    "lateral_acceleration": _positive(MAX_ACCELERATION),
    "governor_deceleration": _positive(MAX_ACCELERATION),
    "collision_resolution": _positive(),
    "vehicle_length": _positive(MAX_VEHICLE_SIZE),
    "vehicle_width": _positive(MAX_VEHICLE_SIZE),
    "spawn_min_gap": _non_negative(),
    "s_ref": _positive(MAX_S_REF),
    "s_scale": _positive(MAX_S_SCALE),
    "d_max": _positive(MAX_D_MAX),
    "proximity_threshold": _positive(),
    "reward": Rule(lambda x: isinstance(x, str) and x in REWARD_PRESETS, f"one of {sorted(REWARD_PRESETS)}"),
    "reward_weights": Rule(_weights, f"a dict mapping some of {REWARD_TERMS} to numbers in [-1e6, 1e6]"),
    "shield": _bool(),
    "spawn_queue": _int(0, MAX_VEHICLES),
    "residual_base": Rule(
        lambda x: x is None or (isinstance(x, str) and x in RESIDUAL_BASES), f"null or one of {RESIDUAL_BASES}"
    ),
    "residual_scale": Rule(lambda x: _is_number(x) and 0 < x <= 2, "a number in (0, 2]"),
    "action": Rule(
        _action,
        f"a dict {{'type': one of {list(ACTION_TYPES)}, 'scale': a number in (0, {MAX_PRIORITY_SCALE:g}] "
        f"(seconds for priority, default {DEFAULT_PRIORITY_SCALE:g}; metres for advice, "
        f"default {DEFAULT_ADVICE_SCALE:g}), 'glide': one of {list(GLIDE_VERSION_NAMES)} (the scheduler's "
        f"parameters, default {GLIDE_VERSION_NAMES[0]!r}), 'hold': true or false (advice once given holds "
        f"to the line, default true)}}",
    ),
    "collision_handling": Rule(lambda x: x in COLLISION_HANDLING, f"one of {COLLISION_HANDLING}"),
    "human_share": Rule(_human_share, HUMAN_SHARE_ALLOWED),
    "faults": Rule(lambda x: x is None or isinstance(x, dict), FAULTS_ALLOWED),  # entries: fault_config
    # Rendering (highway-env's viewer reads these).
    "screen_width": _int(1),
    "screen_height": _int(1),
    "scaling": _positive(),
    "centering_position": Rule(
        lambda x: isinstance(x, (list, tuple)) and len(x) == 2 and all(_is_number(v) for v in x),
        "a pair [x, y] of numbers (fractions of the screen)",
    ),
    "offscreen_rendering": Rule(lambda x: x is None or isinstance(x, (bool, np.bool_)), "null, true or false"),
    "real_time_rendering": _bool(),
    "render_agent": _bool(),
    "show_trajectories": _bool(),
}


def _plain(value: Any) -> Any:
    """NumPy scalars as Python numbers (the configuration is written to JSON and YAML)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    return value


def validate_config(config: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    """Merge ``config`` into ``defaults`` and check the result.

    :param config: the user's settings (a subset of the keys of ``defaults``)
    :param defaults: the environment's ``default_config()``
    :return: a new, merged dictionary
    :raises ValueError: naming the key and what is allowed, for an unknown key, a wrong type or an
        impossible value (including ``simulation_frequency`` not a multiple of ``policy_frequency``)
    """
    if not isinstance(config, dict):
        raise ValueError(f"config must be a dict of config keys and values, got {type(config).__name__}")
    unknown = sorted(set(config) - set(defaults))
    if unknown:
        raise ValueError(f"unknown config key(s) {unknown}; allowed keys: {sorted(defaults)}")
    merged = dict(defaults)
    merged.update(config)
    for key, value in merged.items():
        rule = RULES.get(key)
        if rule is not None and not rule.check(value):
            raise ValueError(f"config key {key!r} must be {rule.allowed}, got {value!r}")
        merged[key] = _plain(value)
    if merged["simulation_frequency"] % merged["policy_frequency"]:
        raise ValueError(
            f"config key 'simulation_frequency' must be a multiple of 'policy_frequency', got "
            f"{merged['simulation_frequency']} and {merged['policy_frequency']}"
        )
    if str(merged.get("layout")).startswith(NET_PREFIX):  # the file reads as one junction (once per process)
        try:
            named_layout(merged["layout"], lateral_acceleration=float(merged["lateral_acceleration"]))
        except ImportError as error:
            raise ValueError(f"config key 'layout' reads a SUMO network, but {error}") from None
        except ValueError as error:
            raise ValueError(f"config key 'layout': {error}") from None
    if merged.get("plant") == "sumo":
        try:
            libsumo_module()
        except ImportError as error:
            raise ValueError(f"config key 'plant' is 'sumo', but {error}") from None
    if merged.get("plant") == "sumo" and 1000 % merged["simulation_frequency"]:
        raise ValueError(
            f"config key 'simulation_frequency' must divide 1000 with plant 'sumo' (SUMO's step is a whole number "
            f"of milliseconds: 20 or 10 at the 5 Hz policy), got {merged['simulation_frequency']}"
        )
    if "faults" in merged:  # each entry checked, the defaults filled in
        merged["faults"] = fault_config(merged["faults"], 1.0 / merged["policy_frequency"])
    # Only the given weights change; the other terms keep their default weight (the preset's, when
    # the call names a new preset).
    if "reward" in config and config["reward"] != defaults.get("reward"):
        weights = preset_weights(merged["reward"])
    else:
        weights = dict(defaults.get("reward_weights", {}))
    weights.update(_plain(config.get("reward_weights", {})))
    merged["reward_weights"] = weights
    merged["initial_speed_range"] = [float(v) for v in merged["initial_speed_range"]]
    if "action" in merged:
        merged["action"] = action_config(merged["action"])
        kind = merged["action"]["type"]
        if kind in SCHEDULER_ACTION_TYPES and merged.get("residual_base") is not None:
            raise ValueError(
                f"config key 'residual_base' must be null with action type {kind!r} (the scores drive "
                f"glide's scheduler; there is no acceleration to correct), got {merged['residual_base']!r}"
            )
    return merged
