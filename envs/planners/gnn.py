"""The learned planner: a trained graph policy of any algorithm in :data:`sb3_graph.registry.ALGORITHMS`
(TD3, DDPG, SAC, TQC, CrossQ, PPO, A2C) behind the planner face. It acts with the policy's
deterministic action, as SB3's ``predict(obs, deterministic=True)``: the actor's output, or the mean
of a stochastic policy squashed (SAC, TQC, CrossQ) or clipped (PPO, A2C) as ``predict`` does.

Planner files are what people share, so they load without running code: a weights-only
``.safetensors`` policy file (``sb3-graph export``) or an SB3 ``.zip`` read without unpickling
(:mod:`sb3_graph.files.policy_files`). ``trust_files=True`` (``--trust-planner-files``) restores SB3's full
``Algorithm.load`` for one's own files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from envs.planners.base import Planner
from envs.planners.loading import model_name
from envs.simulation.config import RULES, SCHEDULER_ACTION_TYPES, action_config
from envs.simulation.graph import build_graph_batch, build_observation, num_node_features
from envs.simulation.scene import Scene
from sb3_graph.common.batching import concat_graph_batches
from sb3_graph.files.policy_files import METADATA_KEY, load_policy
from sb3_graph.registry import deterministic_vertex_actions, entry_of_policy


def load_model(path: str | Path, device: str = "cpu", trust_files: bool = False):
    """Load a planner's policy from a ``.safetensors`` policy file or a saved SB3 ``.zip``.

    :param path: the file
    :param device: torch device
    :param trust_files: load a ``.zip`` with its algorithm's SB3 ``load``, which runs the pickles in it
    :return: the policy (``predict``, ``observation_space``)
    :raises ValueError: a file that cannot be loaded safely (``sb3_graph.files.policy_files.PolicyFileError``)
    """
    return load_policy(path, device=device, trust=trust_files).policy


#: Keys of a policy file's planner configuration (``source["planner"]`` of its header): what the
#: environment did around the policy in training, which the planner must do again.
PLANNER_CONFIG_KEYS = ("residual_base", "residual_scale", "vertex_features", "edge_features", "action", "critic_gate")
#: Keys of a planner configuration that are not settings of the environment (what the planner adds at run time).
_PLANNER_ONLY_KEYS = ("critic_gate",)
_PLANNER_CONFIG_DEFAULTS = {
    "residual_base": None,
    "residual_scale": 0.5,
    "vertex_features": [],
    "edge_features": [],
    "action": {"type": "acceleration"},
    "critic_gate": None,
}


def check_planner_config(config: Any, source: str) -> dict[str, Any]:
    """A policy file's planner configuration, checked and completed.

    :param config: ``None`` or a dict with keys among :data:`PLANNER_CONFIG_KEYS`: ``residual_base``
        (a planner of ``envs.simulation.config.RESIDUAL_BASES``) and ``residual_scale`` (in ``(0, 2]``, default 0.5)
        for a residual policy; ``vertex_features`` and ``edge_features``, the observation's feature
        names (the environment config's keys of the same names); ``action``, what the policy's action
        means (the environment config's key: ``{"type": "priority", "scale": 5.0}`` for a policy
        that shifts glide's order, ``{"type": "advice", "scale": 64.0}`` for one that moves glide's
        advice windows, default accelerations); ``critic_gate``, ``null`` (default) or a number >= 0 for a
        priority or advice policy: its scores are used in a scene only where its critics (the smallest of them)
        value them above glide's own plan (the zero action) by more than this margin, else glide plans alone
        (a Q-filter; :meth:`GNNPlanner.critic_gain`)
    :param source: what to name in errors (the file)
    :return: ``vertex_features`` and ``edge_features`` (tuples, default empty), plus ``residual_base``
        and ``residual_scale`` for a residual policy, plus ``action`` (type and scale) for a priority or advice policy
    :raises ValueError: an unknown key, base or feature name, or a scale outside ``(0, 2]`` (as the
        environment config's rules of the same keys)
    """
    config = {} if config is None else config
    if not isinstance(config, dict) or set(config) - set(PLANNER_CONFIG_KEYS):
        raise ValueError(
            f"{source}: planner config must be a dict with keys among {list(PLANNER_CONFIG_KEYS)}, got {config!r}"
        )
    # Each key means what the environment config's key of the same name means: its rule checks it.
    values = {**_PLANNER_CONFIG_DEFAULTS, **config}
    for key in PLANNER_CONFIG_KEYS:
        if key in _PLANNER_ONLY_KEYS:
            continue
        if not RULES[key].check(values[key]):
            raise ValueError(f"{source}: planner config {key} must be {RULES[key].allowed}, got {values[key]!r}")
    checked: dict[str, Any] = {key: tuple(values[key]) for key in ("vertex_features", "edge_features")}
    action = action_config(values["action"])
    if "glide" not in values["action"]:  # written before glide had versions: trained over the first one
        action["glide"] = "guarded"
    gate = values["critic_gate"]
    if gate is not None:
        if isinstance(gate, bool) or not isinstance(gate, (int, float)) or not math.isfinite(gate) or gate < 0:
            raise ValueError(f"{source}: planner config critic_gate must be null or a number >= 0, got {gate!r}")
        if action["type"] not in SCHEDULER_ACTION_TYPES:
            kinds = " or ".join(SCHEDULER_ACTION_TYPES)
            raise ValueError(f"{source}: planner config critic_gate needs an action of type {kinds} (its zero "
                             f"action is glide), got {action['type']!r}")  # fmt: skip
    if action["type"] in SCHEDULER_ACTION_TYPES:
        if values["residual_base"] is not None:
            raise ValueError(f"{source}: planner config residual_base must be null for a {action['type']} policy")
        checked["action"] = action
        if gate is not None:
            checked["critic_gate"] = float(gate)
    if values["residual_base"] is None:
        return checked
    return {**checked, "residual_base": values["residual_base"], "residual_scale": float(values["residual_scale"])}


#: Algorithms whose policy files a ``critic_gate`` can read: critics of one value each (TQC's give quantiles,
#: CrossQ's a batch-normalised pair, PPO and A2C a state value).
GATED_ALGORITHMS = ("TD3", "DDPG", "SAC")


def check_gated_policy(policy: Any, source: str) -> None:
    """Refuse a ``critic_gate`` over a policy without critics that it can read (:data:`GATED_ALGORITHMS`).

    :raises ValueError: naming the file and its algorithm
    """
    entry = entry_of_policy(policy)
    if entry is None or entry.name not in GATED_ALGORITHMS:
        name = type(policy).__name__ if entry is None else entry.name
        raise ValueError(f"{source}: critic_gate needs a policy file of {', '.join(GATED_ALGORITHMS)} (critics of "
                         f"one value each), got {name}")  # fmt: skip


def planner_config_from_env(config: dict[str, Any]) -> dict[str, Any]:
    """The planner configuration of a policy trained in an environment with ``config`` (what ``sb3-graph
    export`` stores for a model of a run folder): its keys among :data:`PLANNER_CONFIG_KEYS`, the action's
    defaults filled in, glide's version included, as the environment used them in training.

    :param config: the run's environment config (``env_kwargs["config"]`` of its ``config.yml``)
    :raises ValueError: a value that the environment's rule of the same key refuses, naming the key
    """
    found = {key: config[key] for key in PLANNER_CONFIG_KEYS if key in config}
    if "action" in found:
        if not RULES["action"].check(found["action"]):
            raise ValueError(f"config key 'action' must be {RULES['action'].allowed}, got {found['action']!r}")
        found["action"] = action_config(found["action"])
    for key in ("vertex_features", "edge_features"):
        if key in found and isinstance(found[key], tuple):
            found[key] = list(found[key])
    check_planner_config(found, "config key")
    return found


def planner_config_of(path: str | Path) -> dict:
    """The planner configuration in a policy file's header (``source["planner"]``, written by
    ``sb3-graph export --planner-config``); ``{}`` for a ``.zip`` or a file without one.

    :param path: a policy file that :func:`load_model` has read
    """
    import json

    from safetensors import safe_open

    path = Path(path)
    if path.suffix != ".safetensors" or not path.is_file():
        return {}
    with safe_open(str(path), framework="pt") as handle:
        text = (handle.metadata() or {}).get(METADATA_KEY, "{}")
    source = json.loads(text).get("source")
    config = source.get("planner") if isinstance(source, dict) else None
    return dict(config) if isinstance(config, dict) else {}


class GNNPlanner(Planner):
    """A trained model answering for every vehicle at once.

    The scene is turned into the model's own graph observation (its ``observation_space``, a
    ``GraphSpace``) by ``envs.simulation.graph.build_observation``; the deterministic action of
    vertex ``i`` in ``[-1, 1]`` times ``scene.a_max`` is the acceleration of vehicle ``i``.

    :param path: the policy file (``.safetensors``) or saved model (``.zip``)
    :param name: the name shown in reports (default: derived from the path)
    :param device: torch device for inference
    :param trust_files: load a ``.zip`` with its algorithm's SB3 ``load`` (runs its pickles)
    """

    # Run inference without SB3's `predict` (see :meth:`predict`); set for loaded SB3 policies only,
    # so that subclasses around other models (a trial's model in training) keep their `predict`.
    _direct = False
    # Feed the graph network a batch built from the scene (see :meth:`vertex_actions`); set at load
    # for a registered graph policy (exactly its class).
    _graph_actor = False
    # Whether the policy's critics were found readable by a critic gate (checked once: :meth:`check_gate`).
    _gate_checked = False
    # The observation's optional features, as in training (the file's planner config).
    vertex_features: tuple[str, ...] = ()
    edge_features: tuple[str, ...] = ()

    def __init__(
        self, path: str | Path, name: str | None = None, device: str = "cpu", trust_files: bool = False
    ) -> None:
        self.path = Path(path)
        super().__init__(name or model_name(self.path))
        self.model = load_model(self.path, device, trust_files=trust_files)
        # What the environment did around the policy in training (a residual base, the observation's
        # features), from the file's header.
        self.planner_config = check_planner_config(planner_config_of(self.path), str(self.path))
        self.vertex_features = self.planner_config["vertex_features"]
        self.edge_features = self.planner_config["edge_features"]
        self.space = self.model.observation_space
        self._check_features(str(self.path))
        self._direct = _plain_sb3_policy(self.model)
        if self._direct:
            self.model.set_training_mode(False)  # once, rather than in every `predict`
        self._graph_actor = self._direct and _plain_graph_actor(self.model)

    def check_capacity(self, max_vehicles: int, source: str = "planner") -> None:
        """Refuse an environment whose scenes can hold more vehicles than the model's graphs.

        :param max_vehicles: the environment's ``max_vehicles``
        :raises ValueError: naming the model's ``max_nodes``
        """
        max_nodes = getattr(self.space, "max_nodes", None)
        if max_nodes is None or getattr(self.space, "node_features", None) != num_node_features(self.vertex_features):
            raise ValueError(f"{source}: the model does not take the intersection's graph observation")
        if max_nodes < max_vehicles:
            raise ValueError(
                f"{source}: the model's graphs hold max_nodes={max_nodes} vehicles, the environment up to "
                f"max_vehicles={max_vehicles}; evaluate with --env-kwargs "
                f"'{{\"config\": {{\"max_vehicles\": {max_nodes}}}}}' or use a model trained for more"
            )

    def _check_features(self, source: str) -> None:
        """Refuse a model whose graph space does not match the feature names of its planner config.

        :raises ValueError: naming both, and how to export the file with the training's names
        """
        node, edge = getattr(self.space, "node_features", None), getattr(self.space, "edge_features", None)
        if node is None:
            return  # not a graph model: check_capacity says so
        if node != num_node_features(self.vertex_features) or edge != len(self.edge_features):
            raise ValueError(
                f"{source}: the model takes {node} vertex and {edge} edge features, its planner config names "
                f"vertex_features={list(self.vertex_features)} (3 + their columns) and "
                f"edge_features={list(self.edge_features)}; export it with the training's names, e.g. "
                f"sb3-graph export MODEL OUT --planner-config "
                f"'{{\"vertex_features\": [...], \"edge_features\": [...]}}'"
            )

    def _observation_kwargs(self) -> dict[str, Any]:
        return {"vertex_feature_names": self.vertex_features, "edge_feature_names": self.edge_features}

    def act(self, scene: Scene) -> np.ndarray:
        n = scene.num_vehicles
        if n == 0:
            return np.zeros(0)
        if self._graph_actor:
            action = np.asarray(self.vertex_actions(scene), dtype=float)
        else:
            obs = build_observation(scene, self.space, **self._observation_kwargs())
            action = np.asarray(self.predict(obs), dtype=float).reshape(-1)[:n]
        return np.clip(action * scene.a_max, scene.a_min, scene.a_max)

    def act_many(self, scenes: Sequence[Scene]) -> list[np.ndarray]:
        """:meth:`act` for the scenes of several runs stepped in lockstep: one forward pass of the
        graph network over the batch of their graphs (the planner keeps no state between scenes).

        At intersection sizes the network's cost is mostly per call, not per vertex, so a batch of
        ``K`` scenes costs far less than ``K`` calls of :meth:`act`.

        :param scenes: one scene per run
        :return: each scene's accelerations, as :meth:`act` answers it (to float tolerance: the
            matmuls run over more rows)
        """
        if not self._graph_actor:
            return [self.act(scene) for scene in scenes]
        import torch

        answers = [np.zeros(0) for _ in scenes]
        busy = [k for k, scene in enumerate(scenes) if scene.num_vehicles]
        if not busy:
            return answers
        policy = self.model
        kwargs = self._observation_kwargs()
        graphs = concat_graph_batches([build_graph_batch(scenes[k], self.space, **kwargs) for k in busy])
        with torch.inference_mode():  # the batch is made outside: see vertex_actions
            vertex = deterministic_vertex_actions(policy, graphs).numpy()
        actions = np.zeros((len(busy), *policy.action_space.shape), dtype=np.float32)
        actions[graphs.batch.numpy(), graphs.node_slot.numpy()] = vertex
        actions = _to_action_bounds(policy, actions)
        for row, k in enumerate(busy):
            scene = scenes[k]
            action = np.asarray(actions[row, : scene.num_vehicles], dtype=float)
            answers[k] = np.clip(action * scene.a_max, scene.a_min, scene.a_max)
        return answers

    def vertex_actions(self, scene: Scene) -> np.ndarray:
        """The policy's deterministic action of each vehicle: :meth:`predict` of
        :func:`~envs.simulation.graph.build_observation`'s observation, first ``n`` slots, without the
        padded observation.

        The graph batch comes straight from the scene (``build_graph_batch``): no padding to
        ``max_nodes``, no SB3 tensor conversion, no unpadding, no padded action. The batch is made
        outside inference mode: the layers cache its aggregation indices for both convolutions,
        which they do not for inference tensors.

        :param scene: at least one vehicle
        :return: ``(n,)`` float32 actions in the action space's range
        """
        import torch

        policy = self.model
        graphs = build_graph_batch(scene, self.space, **self._observation_kwargs())
        with torch.inference_mode():
            vertex = deterministic_vertex_actions(policy, graphs)
        # SB3's unscaling (or clipping) over the whole action space: bounds of any shape, same arithmetic.
        actions = np.zeros(policy.action_space.shape, dtype=np.float32)
        actions[: scene.num_vehicles] = vertex.numpy()
        return _to_action_bounds(policy, actions)[: scene.num_vehicles]

    def check_gate(self) -> None:
        """Refuse a ``critic_gate`` over this policy unless its critics can be read (:func:`check_gated_policy`);
        checked once per planner (``make_planner`` calls it at load, :meth:`critic_gain` before its first use).

        :raises ValueError: naming the file and its algorithm
        """
        if not self._gate_checked:
            check_gated_policy(self.model, str(self.path))
            self._gate_checked = True

    def critic_gain(self, scene: Scene) -> tuple[np.ndarray, float]:
        """The policy's deterministic scores for ``scene`` and how much more its critics value them than the zero
        action: ``min_k Q_k(s, pi(s)) - min_k Q_k(s, 0)`` over the policy's critics (TD3's twin critics; what a
        ``critic_gate`` compares with its margin).

        :param scene: at least one vehicle
        :return: ``(n,)`` scores in ``[-1, 1]`` and the gain (in the units of the training reward)
        :raises ValueError: a policy without critics that the gate can read (:func:`check_gated_policy`)
        """
        import torch

        self.check_gate()
        policy = self.model
        critic = policy.critic
        n = scene.num_vehicles
        obs, _ = policy.obs_to_tensor(build_observation(scene, self.space, **self._observation_kwargs()))
        with torch.no_grad():
            action = policy._predict(obs, deterministic=True).reshape(1, -1)
            action[:, n:] = 0.0  # the padded slots are no vertices of the graph
            # the scores and the zero action as one batch of two graphs: one pass of the critics, not two
            # (0.8x of the gate's time; the gain differs from two passes by float rounding, about 1e-7)
            pair = {key: torch.cat([value, value]) for key, value in obs.items()}
            values = torch.cat(critic(pair, torch.cat([action, torch.zeros_like(action)])), dim=1).min(dim=1).values
            gain = values[0] - values[1]
        return np.clip(action[0, :n].numpy().astype(float), -1.0, 1.0), float(gain)

    def predict(self, obs) -> np.ndarray:
        """The policy's deterministic action, as ``model.predict(obs, deterministic=True)[0]``.

        SB3's ``predict`` switches the network to evaluation mode (a walk over every module) and
        checks its arguments on every call, which costs about as much as the graph network's
        forward pass at intersection sizes; the network is in evaluation mode since loading, so
        this runs the rest of ``predict`` directly (a model with its own ``predict`` keeps it).

        :param obs: one graph observation
        :return: the action, without a batch dimension
        """
        import torch
        from gymnasium import spaces

        policy = self.model
        if not self._direct:
            return policy.predict(obs, deterministic=True)[0]
        obs_tensor, vectorized = policy.obs_to_tensor(obs)
        with torch.no_grad():
            actions = policy._predict(obs_tensor, deterministic=True)
        actions = actions.cpu().numpy().reshape((-1, *policy.action_space.shape))
        if isinstance(policy.action_space, spaces.Box):
            if policy.squash_output:
                actions = policy.unscale_action(actions)
            else:
                actions = np.clip(actions, policy.action_space.low, policy.action_space.high)
        return actions if vectorized else actions.squeeze(axis=0)


def _plain_sb3_policy(model) -> bool:
    """Whether ``model`` is an SB3 policy that uses SB3's own ``predict``."""
    try:
        from stable_baselines3.common.policies import BasePolicy
    except ImportError:
        return False
    return isinstance(model, BasePolicy) and type(model).predict is BasePolicy.predict


def _plain_graph_actor(model) -> bool:
    """Whether ``model`` is exactly a registered graph policy (:data:`sb3_graph.registry.ALGORITHMS`,
    so its ``_predict`` is the graph network's deterministic action: what :meth:`GNNPlanner.vertex_actions` runs)."""
    return entry_of_policy(model) is not None


def _to_action_bounds(policy, actions: np.ndarray) -> np.ndarray:
    """What SB3's ``predict`` does to the network's actions: unscale a squashed policy's, clip the rest."""
    if policy.squash_output:
        return policy.unscale_action(actions)
    return np.clip(actions, policy.action_space.low, policy.action_space.high)
