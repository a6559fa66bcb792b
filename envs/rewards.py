"""Reward of the paper's section "Reward Engineering": ``R = sum_k w_k R_k``.

Terms (unweighted, per policy step, over the vehicles that were planned in the step: present
before it and still present after it, so spawned and removed vehicles do not count):

- ``velocity``: mean over vehicles of the paper's piecewise function of ``v / v_lim``
  (:func:`velocity_reward`: ``1.25 r`` up to 0.8, 1 up to 1.0, ``6 - 5 r`` above); 0 with no vehicle.
- ``action``: ``-mean_i |a_i| / a_max``, the commanded acceleration magnitude normalized to
  ``[0, 1]`` (so the default weight 0.01 is comparable to the other terms); 0 with no vehicle.
- ``idle``: ``-1`` when at least one vehicle is present and all stand still (speed below
  ``STOP_SPEED``), else 0.
- ``proximity``: ``-max_i max(0, 1 - dmin_i / threshold)``, where ``dmin_i`` is the smallest
  Mahalanobis distance (paper eq. 2) from vehicle ``i`` to any other vehicle and ``threshold``
  defaults to 3 (centres 7.5 m apart in line, i.e. a 2.5 m bumper gap for 5 m cars); the
  closest pair of the scene sets the term, in ``[-1, 0]``.
- ``collision``: ``-1`` when any two vehicles overlapped during the step (the episode ends).

Weights (paper, Table "Reward weights") are positive: velocity 0.03, action 0.01, idle 0.01,
proximity 0.2, collision 1.0.
"""

from __future__ import annotations

import numpy as np

from envs.scene import STOP_SPEED

REWARD_TERMS = ("velocity", "action", "idle", "proximity", "collision")
DEFAULT_REWARD_WEIGHTS = {"velocity": 0.03, "action": 0.01, "idle": 0.01, "proximity": 0.2, "collision": 1.0}
DEFAULT_PROXIMITY_THRESHOLD = 3.0


def velocity_reward(ratio: np.ndarray) -> np.ndarray:
    """The paper's velocity reward of ``v / v_lim``.

    :param ratio: speed over lane speed limit
    :return: ``1.25 r`` for ``r <= 0.8``, ``1`` for ``0.8 < r <= 1``, ``6 - 5 r`` above
    """
    ratio = np.asarray(ratio, float)
    return np.where(ratio <= 0.8, 1.25 * ratio, np.where(ratio <= 1.0, 1.0, 6.0 - 5.0 * ratio))


def reward_terms(
    speed: np.ndarray,
    speed_limit: np.ndarray,
    acceleration: np.ndarray,
    a_max: float,
    min_distance: np.ndarray,
    collision: bool,
    proximity_threshold: float = DEFAULT_PROXIMITY_THRESHOLD,
) -> dict[str, float]:
    """Unweighted reward terms of one step.

    :param speed: ``(n,)`` speeds of the planned vehicles after the step [m/s]
    :param speed_limit: ``(n,)`` their lane speed limits [m/s]
    :param acceleration: ``(n,)`` their commanded accelerations [m/s^2]
    :param a_max: largest acceleration magnitude [m/s^2]
    :param min_distance: ``(n,)`` smallest Mahalanobis distance of each to any other vehicle
    :param collision: whether a collision happened during the step
    :param proximity_threshold: Mahalanobis distance below which the proximity penalty starts
    :return: ``term -> value`` for every term of :data:`REWARD_TERMS`
    """
    speed = np.asarray(speed, float)
    n = speed.shape[0]
    if n == 0:
        return {"velocity": 0.0, "action": 0.0, "idle": 0.0, "proximity": 0.0, "collision": -float(collision)}
    closeness = np.maximum(0.0, 1.0 - np.asarray(min_distance, float) / proximity_threshold)
    return {
        "velocity": float(velocity_reward(speed / np.asarray(speed_limit, float)).mean()),
        "action": -float(np.abs(np.asarray(acceleration, float)).mean() / a_max),
        "idle": -float(bool((speed < STOP_SPEED).all())),
        "proximity": -float(closeness.max()),
        "collision": -float(collision),
    }


def weighted(terms: dict[str, float], weights: dict[str, float]) -> dict[str, float]:
    """Each term times its weight (missing weights count as 0)."""
    return {k: float(weights.get(k, 0.0)) * v for k, v in terms.items()}
