"""Planners: one acceleration per vehicle for a given scene (see :class:`Planner`).

``make_planner(spec)`` builds one from a command-line word: ``"pr"`` (static priority rules),
``"fifo"`` (first in, first out per group of conflicting paths) or the path of a learned GNN
planner: a weights-only ``.safetensors`` policy file (``sb3-graph export``) or a saved SB3
``.zip``, both loaded without running code from the file (see :mod:`envs.planners.gnn`).
"""

from __future__ import annotations

from pathlib import Path

from envs.planners.base import Planner
from envs.planners.fifo import FIFOPlanner
from envs.planners.priority_rules import PriorityRulesPlanner

BASELINES: dict[str, type[Planner]] = {"pr": PriorityRulesPlanner, "fifo": FIFOPlanner}
# File suffixes of learned planners.
MODEL_SUFFIXES = (".safetensors", ".zip")


def check_planner_spec(spec: str) -> str:
    """Validate a planner word without building it (cheap: no model is loaded).

    :param spec: ``"pr"``, ``"fifo"`` or the path of a readable ``.safetensors`` or ``.zip`` model file
    :return: the normalised spec (lower-case baseline name, or the path as given)
    :raises ValueError: anything else, with the accepted values in the message
    """
    key = str(spec).strip()
    if key.lower() in BASELINES:
        return key.lower()
    path = Path(key)
    if path.suffix in MODEL_SUFFIXES and path.is_file():
        try:
            with path.open("rb"):
                pass
        except OSError as error:
            raise ValueError(f"planner {spec!r}: model file is not readable ({error})") from error
        return key
    raise ValueError(
        f"planner {spec!r} is neither a baseline ({', '.join(BASELINES)}) "
        "nor a readable model file (a .safetensors policy file written by sb3-graph export, "
        "or a .zip written by model.save)"
    )


def make_planner(spec: str, trust_files: bool = False) -> Planner:
    """Build a planner from its command-line word.

    :param spec: ``"pr"``, ``"fifo"`` or the path of a ``.safetensors`` policy file or saved ``.zip``
    :param trust_files: load a ``.zip`` with SB3's ``TD3.load``, which runs the pickles in it
        (``--trust-planner-files``; only for one's own files)
    :return: the planner
    :raises ValueError: unknown word, or a model file that cannot be loaded safely
    """
    key = check_planner_spec(spec)
    if key in BASELINES:
        return BASELINES[key]()
    from envs.planners.gnn import GNNPlanner

    return GNNPlanner(key, trust_files=trust_files)


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
    "BASELINES",
    "MODEL_SUFFIXES",
    "FIFOPlanner",
    "Planner",
    "PriorityRulesPlanner",
    "check_planner_spec",
    "make_planner",
    "planner_name",
]
