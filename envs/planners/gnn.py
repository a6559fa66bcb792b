"""The learned planner: a trained SB3 model (TD3 with a graph policy) behind the planner face."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from envs.planners.base import Planner
from envs.scene import Scene


def load_model(path: str | Path, device: str = "cpu"):
    """Load a saved SB3 model: ``sb3_graph.TD3`` when available, else ``stable_baselines3.TD3``.

    :param path: the ``.zip`` written by ``model.save``
    :param device: torch device
    :return: the model
    """
    try:
        from sb3_graph import TD3  # type: ignore[attr-defined]
    except ImportError:
        from stable_baselines3 import TD3
    return TD3.load(str(path), device=device)


class GNNPlanner(Planner):
    """A trained model answering for every vehicle at once.

    The scene is turned into the model's own graph observation (its ``observation_space``, a
    ``GraphSpace``) by ``envs.scene_graph.build_observation``; the deterministic action of
    vertex ``i`` in ``[-1, 1]`` times ``scene.a_max`` is the acceleration of vehicle ``i``.

    :param path: the saved model (``.zip``)
    :param name: the name shown in reports (default: derived from the path)
    :param device: torch device for inference
    """

    def __init__(self, path: str | Path, name: str | None = None, device: str = "cpu") -> None:
        self.path = Path(path)
        super().__init__(name or model_name(self.path))
        self.model = load_model(self.path, device)
        self.space = self.model.observation_space

    def act(self, scene: Scene) -> np.ndarray:
        from envs.scene_graph import build_observation

        n = scene.num_vehicles
        if n == 0:
            return np.zeros(0)
        obs = build_observation(scene, self.space)
        action, _ = self.model.predict(obs, deterministic=True)
        action = np.asarray(action, dtype=float).reshape(-1)[:n]
        return np.clip(action * scene.a_max, scene.a_min, scene.a_max)


def model_name(path: Path) -> str:
    """Report name of a model file: ``RL:<folder>`` for ``best_model.zip`` and the like, else ``RL:<stem>``.

    :param path: the model file
    :return: the name
    """
    stem = path.stem
    if stem in ("best_model", "final_model", "model") and path.parent.name:
        return f"RL:{path.parent.name}"
    return f"RL:{stem}"
