"""Rewards of the intersection: ``R = sum_k w_k R_k`` over named terms, in two presets.

Every step computes every term (``info["reward_terms"]``); the weights choose the reward. The
``reward`` config key names the preset whose weights are the defaults (:data:`REWARD_PRESETS`);
``reward_weights`` changes some of them.

**The task preset** (``reward: task``, the default). The paper's reward ranks planners opposite to
flow and delay (docs/training.md, "The reward check"): its velocity term is a mean over the vehicles in the
scene, so a vehicle held out at the spawn point costs nothing and a crossing earns nothing, and
its proximity and action terms punish the dense platoons that the shield makes safe. The task
terms are sums over vehicles in the units of the task metrics:

- ``throughput``: vehicles whose centre passed the intersection exit in the step (count);
- ``delay``: ``-sum_i dt max(0, 1 - v_i / v_lim_i)`` over the vehicles in the scene, plus ``-dt``
  for each scheduled vehicle still waiting to enter (vehicle-seconds lost against driving at the
  lane limit; summed over a run it is the delay of every scheduled vehicle, the metric's own sum);
- ``stop``: ``-`` the vehicles that stopped for the first time in the episode (the stop ratio's count);
- ``shield``: ``-sum_i |a_proposed_i - a_executed_i| / a_max`` when the environment trains behind
  the shield (``shield: true``): the policy learns what the shield would do; 0 without it;
- ``collision``: as in the paper's preset (``-1`` in a step with a collision), weighed heavily.

**The paper's preset** (``reward: paper``): section "Reward Engineering", Table I. Terms
(unweighted, per policy step, over the vehicles that were planned in the step: present
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

from envs.simulation.scene import STOP_SPEED

PAPER_TERMS = ("velocity", "action", "idle", "proximity", "collision")
TASK_TERMS = ("throughput", "delay", "stop", "shield")
REWARD_TERMS = PAPER_TERMS + TASK_TERMS
PAPER_REWARD_WEIGHTS = {"velocity": 0.03, "action": 0.01, "idle": 0.01, "proximity": 0.2, "collision": 1.0}
# In units of 10 vehicle-seconds of delay (so rewards per step stay of order 1 for the critic): a
# crossing is worth 2 s, a new stop costs 2 s, a collision 50 s, and a full override (from +a_max to
# -a_max) 0.2 s per vehicle and step: small, so that the policy learns where the shield would
# intervene without being paid to brake.
TASK_REWARD_WEIGHTS = {"throughput": 0.2, "delay": 0.1, "stop": 0.2, "collision": 5.0, "shield": 0.01}
REWARD_PRESETS = {"task": TASK_REWARD_WEIGHTS, "paper": PAPER_REWARD_WEIGHTS}
DEFAULT_REWARD = "task"
DEFAULT_REWARD_WEIGHTS = REWARD_PRESETS[DEFAULT_REWARD]
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


def task_reward_terms(
    speed: np.ndarray,
    speed_limit: np.ndarray,
    dt: float,
    waiting: int,
    crossed: int,
    new_stops: int,
    shield_gap: float = 0.0,
) -> dict[str, float]:
    """Unweighted task terms of one step (see the module docstring).

    :param speed: ``(n,)`` speeds of the vehicles in the scene after the step [m/s]
    :param speed_limit: ``(n,)`` their lane speed limits [m/s]
    :param dt: the policy period [s]
    :param waiting: scheduled vehicles still waiting to enter after the step
    :param crossed: vehicles that passed the intersection exit during the step
    :param new_stops: vehicles that stopped for the first time in the episode during the step
    :param shield_gap: ``sum_i |proposed_i - executed_i| / a_max`` (0 without the shield)
    :return: ``term -> value`` for every term of :data:`TASK_TERMS`
    """
    ratio = np.asarray(speed, float) / np.asarray(speed_limit, float)
    lost = float(np.maximum(0.0, 1.0 - ratio).sum()) + float(waiting)
    return {
        "throughput": float(crossed),
        "delay": -dt * lost,
        "stop": -float(new_stops),
        "shield": -float(shield_gap),
    }


def preset_weights(reward: str) -> dict[str, float]:
    """The weights of a named reward preset.

    :param reward: a key of :data:`REWARD_PRESETS`
    :raises ValueError: naming the allowed presets
    """
    if reward not in REWARD_PRESETS:
        raise ValueError(f"reward must be one of {sorted(REWARD_PRESETS)}, got {reward!r}")
    return dict(REWARD_PRESETS[reward])


def weighted(terms: dict[str, float], weights: dict[str, float]) -> dict[str, float]:
    """Each term times its weight (missing weights count as 0)."""
    return {k: float(weights.get(k, 0.0)) * v for k, v in terms.items()}
