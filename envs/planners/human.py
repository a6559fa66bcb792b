"""The human driver of mixed traffic (issue 39): IDM car following with the static priority rules.

A human-driven vehicle cannot be commanded: the environment replaces whatever a planner (or the
shield) asks of it by this model's acceleration, inside the simulation step. The model is the PR
baseline (:class:`envs.planners.priority_rules.PriorityRulesPlanner`) applied to the whole scene:
a human driver yields at its stop point to every vehicle of higher precedence by road and maneuver,
automated or not, and goes before the others, whatever a planner had planned for them.
"""

from __future__ import annotations

from envs.planners.priority_rules import PriorityRulesPlanner


class HumanDriver(PriorityRulesPlanner):
    """The PR baseline as the model of a human driver (see the module docstring)."""

    default_name = "human"
