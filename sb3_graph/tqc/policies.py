"""TQC policy with the relational GNN actor of SAC and graph quantile critics."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from sb3_contrib.tqc.policies import TQCPolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import Schedule
from torch import Tensor, nn

from sb3_graph.common.batching import GraphBatch
from sb3_graph.common.networks import (
    GraphCritic,
    GraphPolicyParameters,
    fast_optimizer_kwargs,
    graph_dims,
)
from sb3_graph.sac.policies import GraphSACActor, _no_sde


class GraphQuantileCritic(GraphCritic):
    """``n_critics`` graph networks, each with ``n_quantiles`` outputs: sb3-contrib's TQC ``Critic``
    interface (``forward`` returns ``(B, n_critics, n_quantiles)``).

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param n_quantiles: quantiles per critic
    :param n_critics: number of critic networks
    :param kwargs: the graph network options of :class:`~sb3_graph.common.networks.GraphCritic`
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        n_quantiles: int = 25,
        n_critics: int = 2,
        **kwargs: Any,
    ) -> None:
        super().__init__(observation_space, action_space, n_critics=n_critics, n_outputs=n_quantiles, **kwargs)
        self.n_quantiles = n_quantiles
        self.quantiles_total = n_quantiles * n_critics

    def forward(self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor) -> Tensor:  # type: ignore[override]
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions
        :return: ``(B, n_critics, n_quantiles)``
        """
        return torch.stack(super().forward(obs, actions), dim=1)


class GraphTQCPolicy(GraphPolicyParameters, TQCPolicy):
    """TQC policy (sb3-contrib) with the graph actor of :class:`~sb3_graph.GraphSACPolicy` (per-vertex
    squashed Gaussian) and :class:`GraphQuantileCritic` critics.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param lr_schedule: learning rate schedule
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output sizes of the relational convolutions
    :param aggregation: aggregation over the in-neighbours of one relation: ``max``, ``mean``, ``sum``
    :param pooling: critic pooling over a graph's vertices: ``max``, ``mean``, ``sum``
    :param activation_fn: activation function
    :param use_sde: must be False (gSDE is not supported)
    :param log_std_init: unused, kept for the signature
    :param use_expln: unused, kept for the signature
    :param clip_mean: unused, kept for the signature
    :param features_extractor_class: not used
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param optimizer_class: optimizer, ``torch.optim.Adam`` by default
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate (Adam and AdamW:
        ``foreach=True`` unless given otherwise, see :func:`~sb3_graph.common.networks.fast_optimizer_kwargs`)
    :param n_quantiles: quantiles per critic
    :param n_critics: number of critic networks
    :param share_features_extractor: not used
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param use_edge_features: feed the space's edge features (if it has any) into every convolution
    """

    actor: GraphSACActor  # type: ignore[assignment]
    critic: GraphQuantileCritic  # type: ignore[assignment]
    critic_target: GraphQuantileCritic  # type: ignore[assignment]

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        encoder_dim: int = 64,
        conv_dims: Sequence[int] = (64, 64),
        aggregation: str = "max",
        pooling: str = "max",
        activation_fn: type[nn.Module] = nn.ReLU,
        use_sde: bool = False,
        log_std_init: float = -3,
        use_expln: bool = False,
        clip_mean: float = 2.0,
        features_extractor_class: type = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[torch.optim.Optimizer] = torch.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_quantiles: int = 25,
        n_critics: int = 2,
        share_features_extractor: bool = False,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        use_edge_features: bool = True,
    ) -> None:
        graph_dims(observation_space, action_space)
        _no_sde(use_sde, "GraphTQCPolicy")
        self._set_graph_kwargs(
            observation_space, "GraphTQCPolicy", encoder_dim, conv_dims, aggregation, activation_fn, use_edge_features,
            net_arch, pooling,
        )  # fmt: skip
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[],
            activation_fn=activation_fn,
            use_sde=False,
            log_std_init=log_std_init,
            use_expln=use_expln,
            clip_mean=clip_mean,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=fast_optimizer_kwargs(optimizer_class, optimizer_kwargs),
            n_quantiles=n_quantiles,
            n_critics=n_critics,
            share_features_extractor=False,
        )

    def make_actor(self, features_extractor: Any = None) -> GraphSACActor:  # type: ignore[override]
        return GraphSACActor(self.observation_space, self.action_space, **self.graph_kwargs).to(self.device)

    def make_critic(self, features_extractor: Any = None) -> GraphQuantileCritic:  # type: ignore[override]
        return GraphQuantileCritic(
            self.observation_space,
            self.action_space,
            n_quantiles=self.critic_kwargs["n_quantiles"],
            n_critics=self.critic_kwargs["n_critics"],
            pooling=self.pooling,
            **self.graph_kwargs,
        ).to(self.device)
