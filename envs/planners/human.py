"""The human driver of mixed traffic (issue 39): IDM car following with the static priority rules.

A human-driven vehicle cannot be commanded: the environment replaces whatever a planner (or the
shield) asks of it by this model's acceleration, inside the simulation step. The model is the PR
baseline (:class:`envs.planners.priority_rules.PriorityRulesPlanner`) applied to the whole scene:
a human driver yields at its stop point to every vehicle of higher precedence by road and maneuver,
automated or not, and goes before the others, whatever a planner had planned for them.
"""

from __future__ import annotations

import numpy as np

from envs.planners.idm import accelerations_with_stops
from envs.planners.priority_rules import PriorityRulesPlanner
from envs.simulation.scene import Scene


class HumanDriver(PriorityRulesPlanner):
    """The PR baseline as the model of a human driver (see the module docstring)."""

    default_name = "human"


def human_commands(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """What the human drivers of a scene do now, as the environment will apply it.

    :param scene: the vehicles now
    :return: ``(n,)`` the human model's accelerations (every row) and ``(n,)`` bool: human drivers
        that the priority rules do not hold at their stop point now (they go, whatever automated
        vehicles do: a planner and the shield must treat them as uncontrollable)
    """
    human = scene.humans
    if not human.any():
        return np.zeros(scene.num_vehicles), np.zeros(scene.num_vehicles, bool)
    driver = HumanDriver()
    blocked = driver.blocked(scene)
    acc = accelerations_with_stops(scene, blocked, driver.crossing, driver.idm)
    return acc, human & ~blocked
