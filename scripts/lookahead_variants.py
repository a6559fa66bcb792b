"""``lookahead``'s other settings, as planner classes for ``--planner FILE:CLASS`` (docs/baselines.md)::

    sb3-graph evaluate --planner lookahead+shield --planner scripts/lookahead_variants.py:PerApproach+shield \\
        --planner scripts/lookahead_variants.py:StopPrice5+shield --trust-planner-files \\
        --scenarios 10 --duration 100 --seed 5000 --jobs 1
"""

from __future__ import annotations

from envs.planners.lookahead import LookaheadParams, LookaheadPlanner


class PerApproach(LookaheadPlanner):
    """After the global window, a greedy pass that tries each candidate on one approach road at a time."""

    def __init__(self) -> None:
        super().__init__("LookaheadPerApproach", LookaheadParams(per_approach=True))


class StopPrice5(LookaheadPlanner):
    """A stop priced at 5 s of delay instead of 2 s."""

    def __init__(self) -> None:
        super().__init__("LookaheadStop5", LookaheadParams(stop_price=5.0))


class Rollouts3Hz(LookaheadPlanner):
    """Rollouts that decide 3 times a second instead of 5 (40 % fewer planning steps per search)."""

    def __init__(self) -> None:
        super().__init__("Lookahead3Hz", LookaheadParams(rollout_frequency=3))


class Hold(LookaheadPlanner):
    """Advice once given holds to the line (glide's rule for a policy's windows): a search changes only the
    vehicles not yet advised."""

    def __init__(self) -> None:
        super().__init__("LookaheadHold", LookaheadParams(hold=True))


class WithStudent(LookaheadPlanner):
    """Expert iteration: the shipped student (an advice policy distilled from ``lookahead``) proposes one more
    candidate, its own windows per vehicle, at every search; the search keeps it where it costs least."""

    def __init__(self) -> None:
        from pathlib import Path

        import envs
        from envs.planners import make_planner

        policy = Path(envs.__file__).parent / "pretrained" / "coop_4way_lookahead" / "best_model.safetensors"
        super().__init__("LookaheadWithStudent", proposer=make_planner(str(policy)))
