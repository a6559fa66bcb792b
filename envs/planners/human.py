"""The human driver of mixed traffic (issue 39): IDM car following with the static priority rules.

A human-driven vehicle cannot be commanded: the environment replaces whatever a planner (or the
shield) asks of it by this model's acceleration, inside the simulation step. The model is the PR
baseline (:class:`envs.planners.priority_rules.PriorityRulesPlanner`) applied to the whole scene:
a human driver yields at its stop point to every vehicle of higher precedence by road and maneuver,
automated or not, and goes before the others, whatever a planner had planned for them.
"""

from __future__ import annotations

import numpy as np

from envs.planners.idm import DEFAULT_IDM, accelerations_with_stops, travel_time
from envs.planners.priority_rules import PriorityRulesPlanner
from envs.simulation.scene import Scene

# A going human at or below this speed [m/s] is predicted in its zones up to the planner's horizon
# (the speed the shield keeps vehicles above inside the box): its speed now bounds no exit.
CRAWL_SPEED = 2.0


class HumanDriver(PriorityRulesPlanner):
    """The PR baseline as the model of a human driver (see the module docstring)."""

    default_name = "human"


def human_commands(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """What the human drivers of a scene do now, as the environment will apply it.

    :param scene: the vehicles now
    :return: ``(n,)`` the human model's accelerations (every row) and ``(n,)`` bool: human drivers
        that the priority rules do not hold at their stop point now (they go, whatever automated
        vehicles do: a planner and the shield must treat them as uncontrollable); where the scene
        carries ``human_intent``, those it says go and not those it says wait (which stand)
    """
    human = scene.humans
    if not human.any():
        return np.zeros(scene.num_vehicles), np.zeros(scene.num_vehicles, bool)
    driver = HumanDriver()
    blocked = driver.blocked(scene)
    acc = accelerations_with_stops(scene, blocked, driver.crossing, driver.idm)
    going = human & ~blocked
    if scene.human_intent is not None:  # what a shield has seen them do against the model (`Scene.human_intent`)
        intent = np.asarray(scene.human_intent)
        going = human & ((going & (intent >= 0)) | (intent > 0))
        acc = np.where(human & (intent < 0), np.minimum(acc, 0.0), acc)
    return acc, going


def approach_limit(scene: Scene, rows: np.ndarray, gap_in: np.ndarray) -> np.ndarray:
    """The highest speed a human driver can reach before it enters a zone: the highest lane limit on its
    route from where it is to the zone (the limit where it is may be a curve's, and rise before the zone),
    at least its speed now. The bound that :func:`human_window`'s earliest entry needs.

    :param scene: the vehicles now
    :param rows: ``(h,)`` the human drivers' rows
    :param gap_in: ``(h,)`` metres each moves before entering its zone (<= 0: in it)
    :return: ``(h,)`` [m/s]
    """
    arc = np.asarray(scene.arc, float)[rows]
    limit = scene.layout.highest_limit(np.asarray(scene.route)[rows], arc, arc + np.maximum(gap_in, 0.0))
    return np.maximum(limit, np.asarray(scene.speed, float)[rows])


def human_window(
    gap_in: np.ndarray,
    gap_out: np.ndarray,
    speed: np.ndarray,
    limit: np.ndarray,
    margin: float,
    crawl_until: float,
    crawl_speed: float = CRAWL_SPEED,
) -> tuple[np.ndarray, np.ndarray]:
    """When a going human driver (one the priority rules let go, :func:`human_commands`) may occupy a
    zone: from its earliest entry (accelerating at IDM's ``acc_max`` up to ``limit``; now if already
    in) to its latest exit at its speed now, widened by ``margin`` on both sides; up to ``crawl_until``
    for a human at a crawl (at most ``crawl_speed``), whose exit the speed now cannot bound. The
    shield's prediction of humans, which AIM, FIFO and glide book as fixed reservations too.

    :param gap_in: ``(h,)`` metres the human moves before its body enters the zone (<= 0: in it)
    :param gap_out: ``(h,)`` metres it moves until its body has left the zone
    :param speed: ``(h,)`` its speed now [m/s]
    :param limit: ``(h,)`` the highest speed it reaches [m/s]
    :param margin: seconds added on both sides
    :param crawl_until: latest exit of a crawling human [s from now]
    :param crawl_speed: at or below this speed [m/s] the exit is ``crawl_until``
    :return: ``(h,)`` start (at least 0) and end of the window [s from now]
    """
    start = travel_time(gap_in, speed, limit, DEFAULT_IDM.acc_max)
    until = np.where(speed > crawl_speed, gap_out / np.maximum(speed, crawl_speed), crawl_until)
    return np.maximum(start - margin, 0.0), until + margin
