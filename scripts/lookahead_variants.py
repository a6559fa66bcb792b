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
