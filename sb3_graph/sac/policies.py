"""Relational GNN actor with a per-vertex tanh-squashed Gaussian, and the SAC policy built on it.

The same actor serves SAC, TQC (:mod:`sb3_graph.tqc`) and CrossQ (:mod:`sb3_graph.crossq`): a
relational trunk, then a dense head shared by all vertices that outputs each vertex's mean and log
standard deviation; an action is ``tanh(u)`` with ``u ~ N(mean, std^2)`` per real vertex, and its
log-probability is the sum over the graph's real vertices (:mod:`sb3_graph.common.distributions`).
Padded action slots are exactly 0 and carry no probability.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.sac.policies import SACPolicy
from torch import Tensor, nn

from sb3_graph.common.batching import GraphBatch, as_graph_batch, batch_to_padded
from sb3_graph.common.distributions import LOG_STD_MAX, LOG_STD_MIN, squashed_sample, sum_per_graph
from sb3_graph.common.networks import (
    GraphCritic,
    GraphPolicyParameters,
    GraphTrunk,
    fast_optimizer_kwargs,
    graph_dims,
)


class GraphSACActor(BasePolicy):
    """Stochastic graph actor: per-vertex squashed Gaussian (SB3's SAC ``Actor`` interface).

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over in-neighbours of one relation
    :param activation_fn: activation function
    :param normalize_images: unused, kept for SB3's signature
    :param edge_dim: edge features read by the convolutions (0: none)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        encoder_dim: int = 64,
        conv_dims: Sequence[int] = (64, 64),
        aggregation: str = "max",
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        edge_dim: int = 0,
    ) -> None:
        super().__init__(
            observation_space, action_space, features_extractor=None, normalize_images=False, squash_output=True
        )
        _, node_features, num_relations = graph_dims(observation_space, action_space)
        self.encoder_dim = encoder_dim
        self.conv_dims = list(conv_dims)
        self.aggregation = aggregation
        self.activation_fn = activation_fn
        self.edge_dim = edge_dim
        self.trunk = GraphTrunk(
            node_features, num_relations, encoder_dim, conv_dims, aggregation, activation_fn, edge_dim
        )
        self.head = nn.Linear(self.trunk.out_dim, 2)  # mean and log std of each vertex
        #: Mean real-vertex count of the last batch passed to action_log_prob with gradients enabled
        #: (the batch's observations in SB3's ``train``; see VertexEntropyMixin).
        self.last_mean_vertices: float | None = None

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            encoder_dim=self.encoder_dim,
            conv_dims=self.conv_dims,
            aggregation=self.aggregation,
            activation_fn=self.activation_fn,
            edge_dim=self.edge_dim,
        )
        return data

    def vertex_distribution(self, graphs: GraphBatch) -> tuple[Tensor, Tensor]:
        """``(N,)`` mean and ``(N,)`` log std (clamped to SB3's ``[-20, 2]``) of each real vertex's
        pre-squash Gaussian."""
        params = self.head(self.trunk.embed(graphs))
        return params[:, 0], params[:, 1].clamp(LOG_STD_MIN, LOG_STD_MAX)

    def forward(self, obs: GraphBatch | Mapping[str, Tensor], deterministic: bool = False) -> Tensor:
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param deterministic: ``tanh(mean)`` instead of a sample
        :return: ``(B, max_nodes)`` actions in ``(-1, 1)``, 0 in padded slots
        """
        graphs = as_graph_batch(obs)
        actions, _ = squashed_sample(*self.vertex_distribution(graphs), deterministic=deterministic)
        return batch_to_padded(actions, graphs)

    def action_log_prob(self, obs: GraphBatch | Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Sample actions and their log-probabilities.

        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :return: ``(B, max_nodes)`` actions (0 in padded slots) and ``(B,)`` log-probabilities,
            each the sum over the graph's real vertices (0 for an empty graph)
        """
        graphs = as_graph_batch(obs)
        actions, log_prob = squashed_sample(*self.vertex_distribution(graphs))
        if torch.is_grad_enabled():  # the observations' call; the next observations' call runs under no_grad
            self.last_mean_vertices = graphs.num_nodes / max(graphs.num_graphs, 1)
        return batch_to_padded(actions, graphs), sum_per_graph(log_prob, graphs)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> Tensor:
        return self(observation, deterministic)

    def reset_noise(self, batch_size: int = 1) -> None:
        """No-op: gSDE is not supported by the graph actor."""

    def set_bn_training_mode(self, mode: bool) -> None:
        """No-op (CrossQ's interface): the graph actor has no batch normalization."""


def _no_sde(use_sde: bool, owner: str) -> None:
    if use_sde:
        raise ValueError(f"{owner}: use_sde=True (gSDE) is not supported by the graph actor; use use_sde=False")


class GraphSACPolicy(GraphPolicyParameters, SACPolicy):
    """SAC policy with a relational GNN actor (per-vertex squashed Gaussian) and graph critics.

    The critics are TD3's graph critics (:class:`~sb3_graph.common.networks.GraphCritic`): each vertex's
    action joins its features, and a padded slot's action never reaches them. Works with
    :class:`sb3_graph.SAC` (graph replay buffer, entropy target per real vertex) and with stock
    ``stable_baselines3.SAC(GraphSACPolicy, env)`` (padded ``DictReplayBuffer``, SB3's entropy target
    ``-max_nodes``).

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param lr_schedule: learning rate schedule
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output sizes of the relational convolutions
    :param aggregation: aggregation over the in-neighbours of one relation: ``max``, ``mean``, ``sum``
    :param pooling: critic pooling over a graph's vertices: ``max``, ``mean``, ``sum``
    :param activation_fn: activation function
    :param use_sde: must be False (gSDE is not supported)
    :param log_std_init: unused (the log std is an output of the head), kept for SB3's signature
    :param use_expln: unused, kept for SB3's signature
    :param clip_mean: unused, kept for SB3's signature
    :param features_extractor_class: not used (graphs go straight to the networks)
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param optimizer_class: optimizer, ``torch.optim.Adam`` by default
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate (Adam and AdamW:
        ``foreach=True`` unless given otherwise, see :func:`~sb3_graph.common.networks.fast_optimizer_kwargs`)
    :param n_critics: number of critic networks
    :param share_features_extractor: not used (nothing to share)
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param use_edge_features: feed the space's edge features (if it has any) into every convolution
    """

    actor: GraphSACActor  # type: ignore[assignment]
    critic: GraphCritic  # type: ignore[assignment]
    critic_target: GraphCritic  # type: ignore[assignment]

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
        n_critics: int = 2,
        share_features_extractor: bool = False,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        use_edge_features: bool = True,
    ) -> None:
        graph_dims(observation_space, action_space)
        _no_sde(use_sde, "GraphSACPolicy")
        self._set_graph_kwargs(
            observation_space, "GraphSACPolicy", encoder_dim, conv_dims, aggregation, activation_fn, use_edge_features,
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
            n_critics=n_critics,
            share_features_extractor=False,
        )

    def make_actor(self, features_extractor: Any = None) -> GraphSACActor:  # type: ignore[override]
        return GraphSACActor(self.observation_space, self.action_space, **self.graph_kwargs).to(self.device)

    def make_critic(self, features_extractor: Any = None) -> GraphCritic:  # type: ignore[override]
        return GraphCritic(
            self.observation_space,
            self.action_space,
            pooling=self.pooling,
            n_critics=self.critic_kwargs["n_critics"],
            **self.graph_kwargs,
        ).to(self.device)
