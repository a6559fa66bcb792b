"""Relational graph neural network actor and critics for TD3 and DDPG (Klimke et al., IEEE IV 2022).

The actor maps a graph to one action per vertex; each critic joins every vertex's action to its
features, runs the same kind of trunk, pools over the graph's vertices and outputs one Q value
(:mod:`sb3_graph.common.networks`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.td3.policies import TD3Policy
from torch import Tensor, nn

from sb3_graph.common.batching import GraphBatch, as_graph_batch, batch_to_padded
from sb3_graph.common.networks import (
    GraphCritic,
    GraphPolicyParameters,
    GraphTrunk,
    fast_optimizer_kwargs,
    graph_dims,
)


class GraphActor(BasePolicy):
    """TD3 actor: a relational trunk and a dense head shared across vertices, tanh, one action per
    vertex; padded slots are exactly 0.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over in-neighbours of one relation
    :param activation_fn: activation function
    :param normalize_images: unused (graphs are not images), kept for SB3's signature
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
            observation_space,
            action_space,
            features_extractor=None,
            normalize_images=False,
            squash_output=True,
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
        self.head = nn.Linear(self.trunk.out_dim, 1)

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

    def vertex_actions(self, graphs: GraphBatch) -> Tensor:
        """``(N,)`` action of each real vertex in ``[-1, 1]``."""
        return torch.tanh(self.head(self.trunk.embed(graphs))).squeeze(-1)

    def forward(self, obs: GraphBatch | Mapping[str, Tensor]) -> Tensor:
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :return: ``(B, max_nodes)`` actions, 0 in padded slots
        """
        graphs = as_graph_batch(obs)
        return batch_to_padded(self.vertex_actions(graphs), graphs)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> Tensor:
        # TD3's actor is deterministic.
        return self(observation)


class GraphPolicy(GraphPolicyParameters, TD3Policy):
    """TD3 (and DDPG) policy with relational graph neural network actor and critics (Klimke et al. 2022).

    Defaults: vertex encoder 64, two relational convolutions 64 -> 64 with max aggregation per
    relation, ReLU, max pooling in the critics; the paper's figure gives the layer types but its
    sizes are not in the text, so 64 is our documented choice. The observation space must be a
    :class:`~sb3_graph.GraphSpace` and the action space ``Box(-1, 1, (max_nodes,))`` (symmetric
    bounds: a padded action of 0 then maps to the middle of the range).

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param lr_schedule: learning rate schedule
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output sizes of the relational convolutions
    :param aggregation: aggregation over the in-neighbours of one relation: ``max``, ``mean``, ``sum``
    :param pooling: critic pooling over a graph's vertices: ``max``, ``mean``, ``sum``
    :param activation_fn: activation function
    :param optimizer_class: optimizer, ``torch.optim.Adam`` by default
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate (Adam and AdamW:
        ``foreach=True`` unless given otherwise, see :func:`~sb3_graph.common.networks.fast_optimizer_kwargs`)
    :param n_critics: number of critic networks (TD3: 2)
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param features_extractor_class: not used (graphs go straight to the networks)
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param share_features_extractor: not used (nothing to share)
    :param use_edge_features: feed the space's edge features (if it has any) into every convolution
    """

    actor: GraphActor  # type: ignore[assignment]
    actor_target: GraphActor  # type: ignore[assignment]
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
        optimizer_class: type[torch.optim.Optimizer] = torch.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        n_critics: int = 2,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        features_extractor_class: type = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        share_features_extractor: bool = False,
        use_edge_features: bool = True,
    ) -> None:
        graph_dims(observation_space, action_space)
        # Read by make_actor / make_critic, which TD3Policy.__init__ calls.
        self._set_graph_kwargs(
            observation_space, "GraphPolicy", encoder_dim, conv_dims, aggregation, activation_fn, use_edge_features,
            net_arch, pooling,
        )  # fmt: skip
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[],
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=fast_optimizer_kwargs(optimizer_class, optimizer_kwargs),
            n_critics=n_critics,
            share_features_extractor=share_features_extractor,
        )

    def make_actor(self, features_extractor: Any = None) -> GraphActor:  # type: ignore[override]
        return GraphActor(self.observation_space, self.action_space, **self.graph_kwargs).to(self.device)

    def make_critic(self, features_extractor: Any = None) -> GraphCritic:  # type: ignore[override]
        return GraphCritic(
            self.observation_space,
            self.action_space,
            pooling=self.pooling,
            n_critics=self.critic_kwargs["n_critics"],
            **self.graph_kwargs,
        ).to(self.device)


#: The same class under the name the other algorithms' graph policies follow.
GraphTD3Policy = GraphPolicy
