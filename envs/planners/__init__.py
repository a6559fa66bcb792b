"""Planners: one acceleration per vehicle for a given scene (see :class:`Planner`).

``make_planner(spec)`` builds one from a command-line word: ``"pr"`` (static priority rules),
``"fifo"`` (first in, first out per group of conflicting paths), ``"aim"`` (reservations per
conflict zone), ``"signal"`` (an actuated traffic signal), ``"fullthrottle"`` (every vehicle at the
largest acceleration: the greedy planner that behind the shield is the strongest baseline), the path
of a learned GNN planner (a weights-only ``.safetensors`` policy file written by ``sb3-graph
export``, or a saved SB3 ``.zip``, both loaded without running code from the file, see
:mod:`envs.planners.gnn`), or a user class ``path/to/file.py:ClassName`` /
``package.module:ClassName`` (:mod:`envs.planners.loading`), or a planner server
``http://HOST:PORT`` (``sb3-graph serve``, :mod:`envs.serve.client`). The suffix ``+shield`` wraps
any of them in the safety shield (:class:`envs.planners.shield.Shield`). A policy file trained as a
residual policy (its header's planner configuration names a ``residual_base``) is built as
:class:`envs.planners.residual.ResidualPlanner` around that base.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from envs.planners.adversarial import FullThrottle
from envs.planners.aim import AIMPlanner
from envs.planners.base import Planner
from envs.planners.fifo import FIFOPlanner
from envs.planners.glide import GUARDED, GlidePlanner, glide_scheduler
from envs.planners.human import HumanDriver
from envs.planners.loading import (
    check_remote_spec,
    class_planner_name,
    is_class_spec,
    is_remote_spec,
    load_planner_class,
    make_class_planner,
    make_remote_planner,
    model_name,
    remote_planner_name,
)
from envs.planners.lookahead import LookaheadPlanner
from envs.planners.priority import PriorityPlanner
from envs.planners.priority_rules import PriorityRulesPlanner
from envs.planners.residual import ResidualPlanner
from envs.planners.shield import Shield, training_shield
from envs.planners.shield_bounds import DECLARED_BOUNDS, ShieldBounds, parse_shield_bounds
from envs.planners.signal import SignalPlanner
from envs.simulation import hooks

BASELINES: dict[str, type[Planner]] = {
    "pr": PriorityRulesPlanner,
    "fifo": FIFOPlanner,
    "aim": AIMPlanner,
    "signal": SignalPlanner,
    "fullthrottle": FullThrottle,
    "glide": GlidePlanner,
    "lookahead": LookaheadPlanner,
}
# Without the shield, glide keeps IDM car following and AIM's zone guard on its advice (nothing else keeps a gap).
UNSHIELDED: dict[str, Callable[[], Planner]] = {"glide": lambda: GlidePlanner(params=GUARDED)}
# Report names of the built-in planners.
BASELINE_NAMES = {
    "pr": "PR",
    "fifo": "FIFO",
    "aim": "AIM",
    "signal": "SIGNAL",
    "fullthrottle": "FullThrottle",
    "glide": "Glide",
    "lookahead": "Lookahead",
}
# A planner word ending in this is the planner wrapped in the safety shield.
SHIELD_SUFFIX = "+shield"
# File suffixes of learned planners.
MODEL_SUFFIXES = (".safetensors", ".zip")


def check_planner_spec(spec: str) -> str:
    """Validate a planner word without building it (cheap: no model is loaded).

    :param spec: ``"pr"``, ``"fifo"``, ``"aim"``, ``"signal"``, ``"fullthrottle"``, the path of a
        readable ``.safetensors`` or ``.zip`` model file, or a class spec (``file.py:Class``,
        ``package.module:Class``, imported to check it), or a planner server ``http://HOST:PORT``
        (not contacted here), each optionally followed by ``+shield``
    :return: the normalised spec (lower-case baseline name, or the path or class spec as given)
    :raises ValueError: anything else, with the accepted values in the message
    """
    key = str(spec).strip()
    if key.endswith(SHIELD_SUFFIX):
        try:
            return check_planner_spec(key[: -len(SHIELD_SUFFIX)]) + SHIELD_SUFFIX
        except _UnknownWord:  # name the word as typed, suffix and all
            raise _UnknownWord(f"planner {spec!r} is unknown{_suggestion(key)}; {PLANNER_WORDS}") from None
    if key.lower() in BASELINES:
        return key.lower()
    if is_remote_spec(key):
        return check_remote_spec(key)
    if is_class_spec(key):
        load_planner_class(key)
        return key
    path = Path(key)
    if path.suffix in MODEL_SUFFIXES and path.is_file():
        try:
            with path.open("rb"):
                pass
        except OSError as error:
            raise ValueError(f"planner {spec!r}: model file is not readable ({error})") from error
        return key
    if path.suffix in MODEL_SUFFIXES:
        raise ValueError(f"planner {spec!r}: file not found ({path.resolve()}); {PLANNER_WORDS}")
    if path.is_dir():
        raise ValueError(f"planner {spec!r} is a folder, not a model file; {PLANNER_WORDS}")
    raise _UnknownWord(f"planner {spec!r} is unknown{_suggestion(key)}; {PLANNER_WORDS}")


#: What a planner word may be, for the errors of :func:`check_planner_spec`.
PLANNER_WORDS = (
    f"expected a baseline ({', '.join(BASELINES)}), "
    "a model file (a .safetensors policy file written by sb3-graph export, or a .zip written by model.save), "
    "a class (path/to/file.py:ClassName or package.module:ClassName) "
    f"or a planner server (http://HOST:PORT), each optionally followed by {SHIELD_SUFFIX}"
)


class _UnknownWord(ValueError):
    """A planner word that is none of the accepted kinds (not a file that is missing or unreadable)."""


def _suggestion(word: str) -> str:
    """``" (did you mean 'glide'?)"`` for a near miss of a baseline (with or without a misspelt suffix), else ``""``.

    :param word: a planner word that is none of the accepted ones
    """
    import difflib

    head, plus, suffix = word.lower().partition("+")
    close = difflib.get_close_matches(head, list(BASELINES), n=1, cutoff=0.6)
    if not close:
        return ""
    guess = close[0]
    if plus:
        if not difflib.get_close_matches(plus + suffix, [SHIELD_SUFFIX], n=1, cutoff=0.6):
            return ""
        guess += SHIELD_SUFFIX
    return f" (did you mean {guess!r}?)" if guess != word else ""


def make_planner(spec: str, trust_files: bool = False, shield_bounds: ShieldBounds | None = None) -> Planner:
    """Build a planner from its command-line word.

    :param spec: see :func:`check_planner_spec`
    :param trust_files: load a ``.zip`` with SB3's ``TD3.load``, which runs the pickles in it
        (``--trust-planner-files``; only for one's own files)
    :param shield_bounds: the faults the shield of a ``+shield`` word is declared to tolerate (``--shield-bounds``;
        ``None``: the exact world); a shield in a planner server's client keeps the exact world
    :return: the planner
    :raises ValueError: unknown word, or a model file that cannot be loaded safely
    """
    key = check_planner_spec(spec)
    if key.endswith(SHIELD_SUFFIX):
        inner = key[: -len(SHIELD_SUFFIX)]
        if is_remote_spec(inner):  # its misses get the shield's fallback
            return make_remote_planner(inner, shielded=True)
        if inner in BASELINES:
            return Shield(BASELINES[inner](), bounds=shield_bounds)
        return Shield(make_planner(inner, trust_files=trust_files), bounds=shield_bounds)
    if key in BASELINES:
        return UNSHIELDED.get(key, BASELINES[key])()
    if is_remote_spec(key):
        return make_remote_planner(key)
    if is_class_spec(key):
        return make_class_planner(key)
    from envs.planners.gnn import GNNPlanner  # torch: loaded only for a policy file

    planner = GNNPlanner(key, trust_files=trust_files)
    config = planner.planner_config  # checked at load
    if "action" in config:  # a scheduling policy: its scores shift glide's order or its advice windows
        action = config["action"]
        scheduler = glide_scheduler(action["glide"], action["hold"])
        if config.get("critic_gate") is not None:
            planner.check_gate()
        return PriorityPlanner(scheduler, planner, action["scale"], name=planner.name, kind=action["type"],
                               critic_gate=config.get("critic_gate"))  # fmt: skip
    if config.get("residual_base") is None:
        return planner
    base = make_residual_base(config["residual_base"])
    return ResidualPlanner(base, planner, config["residual_scale"], name=planner.name)


def make_residual_base(name: str | None) -> Planner | None:
    """The base planner of a residual policy (``residual_base``), or ``None``.

    :param name: ``None`` or one of :data:`envs.simulation.config.RESIDUAL_BASES`
    """
    return None if name is None else make_planner(name)


def planner_name(spec: str) -> str:
    """Report name of a planner word, without building it.

    :param spec: a valid planner word (see :func:`check_planner_spec`)
    :return: ``"PR"``, ``"FIFO"``, ``"AIM"``, ``"SIGNAL"``, ``"FullThrottle"``, ``"RL:<name>"``, a
        class planner's ``name`` or, for a planner server,
        ``<its planner's name>@HOST:PORT`` (asked from the server); ``+shield`` appended
        for a shielded one
    """
    key = check_planner_spec(spec)
    if key.endswith(SHIELD_SUFFIX):
        return planner_name(key[: -len(SHIELD_SUFFIX)]) + SHIELD_SUFFIX
    if key in BASELINES:
        return BASELINE_NAMES[key]
    if is_remote_spec(key):
        return remote_planner_name(key)
    if is_class_spec(key):
        return class_planner_name(key)
    return model_name(Path(key))


# What the environments train with (envs.simulation.hooks): the planners live on this floor.
hooks.register("shield", training_shield)
hooks.register("residual_base", make_residual_base)
hooks.register("priority", glide_scheduler)
hooks.register("human", HumanDriver)

__all__ = [
    "AIMPlanner",
    "BASELINES",
    "BASELINE_NAMES",
    "DECLARED_BOUNDS",
    "FullThrottle",
    "MODEL_SUFFIXES",
    "FIFOPlanner",
    "GlidePlanner",
    "Planner",
    "PriorityRulesPlanner",
    "SHIELD_SUFFIX",
    "ShieldBounds",
    "SignalPlanner",
    "check_planner_spec",
    "make_planner",
    "make_residual_base",
    "parse_shield_bounds",
    "planner_name",
]
