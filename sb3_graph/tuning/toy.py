"""A stand-in evaluator for ``GraphMaxNeighbour-v0`` (tests and smoke runs of the tuning command).

The toy task has no traffic, so its "task metrics" are named like the intersection's to fit the
objectives, with these meanings (per vertex, over the validation episodes, deterministic actions):

- ``flow_rate``: share of vertices answered within 0.25 of their target (useful output);
- ``collision_rate``: share answered more than 1.0 away (gross errors);
- ``stop_ratio``: share whose output is within 0.05 of 0 (idle output);
- ``delay_mean``: mean absolute error of the answers (how far off, on average).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


def evaluate_max_neighbour(
    model: Any, env_id: str, env_kwargs: dict[str, Any], episodes: int = 3, seed: int = 0
) -> dict[str, float]:
    """Run ``episodes`` validation episodes of the toy env and score the per-vertex answers.

    :param model: a trained SB3 model (``predict``)
    :param env_id: gymnasium id (a :class:`sb3_graph.toy_envs.MaxNeighbourEnv`)
    :param env_kwargs: keyword arguments of ``gym.make``
    :param episodes: validation episodes
    :param seed: episode ``i`` resets with ``seed + i``
    :return: ``flow_rate``, ``collision_rate``, ``stop_ratio``, ``delay_mean`` (see the module docstring),
        ``vertices``
    """
    import sb3_graph.toy_envs  # noqa: F401  (registers the env)

    env = gym.make(env_id, **env_kwargs)
    errors, outputs = [], []
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            done = False
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                n = int(obs["node_mask"].sum())
                obs, _, terminated, truncated, info = env.step(action)
                errors.append(np.abs(np.clip(action[:n], -1, 1) - info["target"]))
                outputs.append(action[:n])
                done = terminated or truncated
    finally:
        env.close()
    error = np.concatenate(errors) if errors else np.zeros(0)
    output = np.concatenate(outputs) if outputs else np.zeros(0)
    if error.size == 0:
        return {"flow_rate": 0.0, "collision_rate": 0.0, "stop_ratio": 0.0, "delay_mean": 0.0, "vertices": 0}
    return {
        "flow_rate": float((error < 0.25).mean()),
        "collision_rate": float((error > 1.0).mean()),
        "stop_ratio": float((np.abs(output) < 0.05).mean()),
        "delay_mean": float(error.mean()),
        "vertices": int(error.size),
    }
