"""Planners: one acceleration per vehicle for a given scene (see :class:`Planner`).

``make_planner(spec)`` builds one from a command-line word: ``"pr"`` (static priority rules),
``"fifo"`` (first in, first out per group of conflicting paths), ``"aim"`` (reservations per
conflict zone), ``"signal"`` (an actuated traffic signal) or the path of a saved SB3 model ``.zip``
(the learned GNN planner).
"""

from __future__ import annotations

from pathlib import Path

from envs.planners.aim import AIMPlanner
from envs.planners.base import Planner
from envs.planners.fifo import FIFOPlanner
from envs.planners.priority_rules import PriorityRulesPlanner
from envs.planners.signal import SignalPlanner

BASELINES: dict[str, type[Planner]] = {
    "pr": PriorityRulesPlanner,
    "fifo": FIFOPlanner,
    "aim": AIMPlanner,
    "signal": SignalPlanner,
}


def check_planner_spec(spec: str) -> str:
    """Validate a planner word without building it (cheap: no model is loaded).

    :param spec: ``"pr"``, ``"fifo"`` or the path of a readable ``.zip`` model file
    :return: the normalised spec (lower-case baseline name, or the path as given)
    :raises ValueError: anything else, with the accepted values in the message
    """
    key = str(spec).strip()
    if key.lower() in BASELINES:
        return key.lower()
    path = Path(key)
    if path.suffix == ".zip" and path.is_file():
        try:
            with path.open("rb"):
                pass
        except OSError as error:
            raise ValueError(f"planner {spec!r}: model file is not readable ({error})") from error
        return key
    raise ValueError(
        f"planner {spec!r} is neither a baseline ({', '.join(BASELINES)}) "
        "nor a readable saved model file (path to a .zip written by model.save)"
    )


def make_planner(spec: str) -> Planner:
    """Build a planner from its command-line word.

    :param spec: ``"pr"``, ``"fifo"`` or the path of a saved SB3 model ``.zip``
    :return: the planner
    :raises ValueError: unknown word or unreadable model file
    """
    key = check_planner_spec(spec)
    if key in BASELINES:
        return BASELINES[key]()
    from envs.planners.gnn import GNNPlanner

    return GNNPlanner(key)


def planner_name(spec: str) -> str:
    """Report name of a planner word, without building it.

    :param spec: a valid planner word (see :func:`check_planner_spec`)
    :return: ``"PR"``, ``"FIFO"`` or ``"RL:<name>"``
    """
    key = check_planner_spec(spec)
    if key in BASELINES:
        return key.upper()
    from envs.planners.gnn import model_name

    return model_name(Path(key))


__all__ = [
    "AIMPlanner",
    "BASELINES",
    "FIFOPlanner",
    "Planner",
    "PriorityRulesPlanner",
    "SignalPlanner",
    "check_planner_spec",
    "make_planner",
    "planner_name",
]
