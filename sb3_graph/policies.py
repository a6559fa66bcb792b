"""Relational graph neural network actor and critics for TD3 (Klimke et al., IEEE IV 2022).

The actor maps a graph to one action per vertex; each critic joins every vertex's action to its
features, runs the same kind of trunk, pools over the graph's vertices and outputs one Q value.
Observations arrive either as a :class:`~sb3_graph.batching.GraphBatch` (from
:class:`~sb3_graph.GraphReplayBuffer`) or as SB3's padded dictionary of tensors (``predict``,
``DictReplayBuffer``); actions are always padded ``(B, max_nodes)`` at this boundary.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.td3.policies import TD3Policy
from torch import Tensor, nn
from torch_geometric.nn import global_add_pool, global_max_pool, global_mean_pool

from sb3_graph.batching import GraphBatch, as_graph_batch, batch_to_padded, derived_indices, gather_vertex_values
from sb3_graph.layers import AGGREGATIONS, RelationalMaxConv, relational_conv, segment_max
from sb3_graph.spaces import EDGE_TYPE, GRAPH_KEYS, X

POOLINGS = {"max": global_max_pool, "mean": global_mean_pool, "sum": global_add_pool}


def graph_dims(observation_space: spaces.Space, action_space: spaces.Space) -> tuple[int, int, int]:
    """``(max_nodes, node_features, num_relations)`` of a graph observation space, checked against
    the action space (one action per vertex slot).

    :param observation_space: a :class:`~sb3_graph.GraphSpace` (or a ``Dict`` with its layout)
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :return: the dimensions
    :raises ValueError: when the spaces do not fit together
    """
    if not isinstance(observation_space, spaces.Dict) or set(observation_space.spaces) != set(GRAPH_KEYS):
        raise ValueError(
            f"GraphPolicy: observation_space must be a GraphSpace (Dict with keys {GRAPH_KEYS}), "
            f"got {observation_space}"
        )
    max_nodes, node_features = observation_space[X].shape
    num_relations = getattr(observation_space, "num_relations", None)
    if num_relations is None:
        num_relations = int(np.max(observation_space[EDGE_TYPE].high)) + 1
    if not isinstance(action_space, spaces.Box) or action_space.shape != (max_nodes,):
        raise ValueError(
            f"GraphPolicy: action_space must be a Box of shape (max_nodes,) = ({max_nodes},), "
            f"got {action_space}"
        )
    return int(max_nodes), int(node_features), int(num_relations)


class GraphTrunk(nn.Module):
    """Vertex encoder (one dense layer shared by all vertices) followed by relational convolutions,
    each followed by the activation.

    :param in_dim: input features per vertex
    :param num_relations: number of edge types
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over the in-neighbours of one relation (``max``, ``mean``, ``sum``)
    :param activation_fn: activation after the encoder and after each convolution
    """

    def __init__(
        self,
        in_dim: int,
        num_relations: int,
        encoder_dim: int = 64,
        conv_dims: Sequence[int] = (64, 64),
        aggregation: str = "max",
        activation_fn: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        self.encoder = nn.Linear(in_dim, encoder_dim)
        dims = [encoder_dim, *conv_dims]
        self.convs = nn.ModuleList(
            RelationalMaxConv(dims[i], dims[i + 1], num_relations, aggr=aggregation)
            for i in range(len(conv_dims))
        )
        self.activation = activation_fn()
        self.out_dim = dims[-1]

    def forward(self, x: Tensor, edge_index: Tensor, edge_type: Tensor) -> Tensor:
        """
        :param x: ``(N, in_dim)`` vertex features
        :param edge_index: ``(2, E)`` long
        :param edge_type: ``(E,)`` long
        :return: ``(N, out_dim)`` vertex embeddings
        """
        return stacked_trunk_forward([self], x, edge_index, edge_type)[0]


def _activate(activation: nn.Module, h: Tensor) -> Tensor:
    # In place for ReLU: every h here is a fresh output that its producer's backward does not read.
    return h.relu_() if type(activation) is nn.ReLU else activation(h)


def stacked_trunk_forward(
    trunks: Sequence[GraphTrunk], x: Tensor, edge_index: Tensor, edge_type: Tensor
) -> Tensor:
    """Run ``K`` trunks of the same shape on the same graph batch at once (batched matmuls, one
    aggregation per layer for all of them); each output equals ``trunks[k](x, edge_index, edge_type)``.

    :param trunks: ``K`` trunks with equal dimensions, aggregation and activation
    :param x: ``(N, in_dim)`` vertex features, shared by all trunks
    :param edge_index: ``(2, E)`` long
    :param edge_type: ``(E,)`` long
    :return: ``(K, N, out_dim)`` vertex embeddings
    """
    first = trunks[0]
    if len(trunks) == 1:  # 2-D tensors: see relational_conv
        h = _activate(first.activation, first.encoder(x))
        for conv in first.convs:
            h = _activate(first.activation, relational_conv([conv], h, edge_index, edge_type))
        return h.unsqueeze(0)
    weight = torch.stack([t.encoder.weight for t in trunks]).transpose(1, 2)
    bias = torch.stack([t.encoder.bias for t in trunks]).unsqueeze(1)
    h = _activate(first.activation, torch.baddbmm(bias, x.expand(len(trunks), -1, -1), weight))
    for layer in range(len(first.convs)):
        convs = [t.convs[layer] for t in trunks]
        h = _activate(first.activation, relational_conv(convs, h, edge_index, edge_type))
    return h


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
        self.trunk = GraphTrunk(
            node_features, num_relations, encoder_dim, conv_dims, aggregation, activation_fn
        )
        self.head = nn.Linear(self.trunk.out_dim, 1)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            encoder_dim=self.encoder_dim,
            conv_dims=self.conv_dims,
            aggregation=self.aggregation,
            activation_fn=self.activation_fn,
        )
        return data

    def vertex_actions(self, graphs: GraphBatch) -> Tensor:
        """``(N,)`` action of each real vertex in ``[-1, 1]``."""
        h = self.trunk(graphs.x, graphs.edge_index, graphs.edge_type)
        return torch.tanh(self.head(h)).squeeze(-1)

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


class GraphQNetwork(nn.Module):
    """One critic: vertex features joined with the vertex's action, a relational trunk, a
    permutation-invariant pooling over each graph's vertices and a linear head.

    :param node_features: features per vertex (the action is appended)
    :param num_relations: number of edge types
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over in-neighbours of one relation
    :param pooling: ``max``, ``mean`` or ``sum`` over the vertices (an empty graph pools to 0)
    :param activation_fn: activation function
    """

    def __init__(
        self,
        node_features: int,
        num_relations: int,
        encoder_dim: int,
        conv_dims: Sequence[int],
        aggregation: str,
        pooling: str,
        activation_fn: type[nn.Module],
    ) -> None:
        super().__init__()
        self.trunk = GraphTrunk(
            node_features + 1, num_relations, encoder_dim, conv_dims, aggregation, activation_fn
        )
        self.pooling = pooling
        self.pool = POOLINGS[pooling]
        self.head = nn.Linear(self.trunk.out_dim, 1)

    def forward(self, graphs: GraphBatch, vertex_actions: Tensor) -> Tensor:
        """
        :param graphs: the batch
        :param vertex_actions: ``(N,)`` action of each real vertex
        :return: ``(B, 1)`` Q values
        """
        return stacked_q_forward([self], graphs, vertex_actions)[0]


def _pool_index(batch: Tensor, num_graphs: int, copies: int) -> tuple[Tensor, int]:
    """Graph id of every vertex of ``copies`` stacked batches (copy ``k``: ids ``+ k * B``) and the
    number of non-empty graphs."""

    def compute() -> tuple[Tensor, int]:
        offsets = torch.arange(copies, device=batch.device).unsqueeze(-1) * num_graphs
        nonempty = int(torch.count_nonzero(torch.bincount(batch, minlength=num_graphs)))
        return (batch + offsets).view(-1), nonempty * copies

    return derived_indices.get((batch,), ("pool", num_graphs, copies), compute)


def stacked_q_forward(q_networks: Sequence[GraphQNetwork], graphs: GraphBatch, vertex_actions: Tensor) -> Tensor:
    """Run ``K`` Q networks of the same shape on the same batch at once; ``out[k]`` equals
    ``q_networks[k](graphs, vertex_actions)``.

    :param q_networks: ``K`` networks with equal dimensions, aggregation, pooling and activation
    :param graphs: the batch
    :param vertex_actions: ``(N,)`` action of each real vertex
    :return: ``(K, B, 1)`` Q values
    """
    copies, num_graphs = len(q_networks), graphs.num_graphs
    x = torch.cat((graphs.x, vertex_actions.unsqueeze(-1).to(graphs.x.dtype)), dim=-1)
    h = stacked_trunk_forward([q.trunk for q in q_networks], x, graphs.edge_index, graphs.edge_type)
    h = h.view(copies * h.size(1), h.size(2))
    index, nonempty = _pool_index(graphs.batch, num_graphs, copies)
    if q_networks[0].pooling == "max":
        pooled = segment_max(h, None, index, copies * num_graphs, nonempty)
    else:
        pooled = q_networks[0].pool(h, index, copies * num_graphs)
    pooled = pooled.view(copies, num_graphs, -1)
    weight = torch.stack([q.head.weight for q in q_networks]).transpose(1, 2)
    bias = torch.stack([q.head.bias for q in q_networks]).unsqueeze(1)
    return torch.baddbmm(bias, pooled, weight)


class GraphCritic(BaseModel):
    """``n_critics`` independent graph Q networks with SB3's ``ContinuousCritic`` interface.

    Each critic reads the action of real vertices only (``actions[batch, node_slot]``), so a padded
    slot's action, TD3's smoothing noise on it, or a padded feature value cannot change Q.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over in-neighbours of one relation
    :param pooling: pooling over the vertices of a graph
    :param activation_fn: activation function
    :param n_critics: number of critic networks
    :param normalize_images: unused, kept for SB3's signature
    :param share_features_extractor: unused (no features extractor), kept for SB3's signature
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        encoder_dim: int = 64,
        conv_dims: Sequence[int] = (64, 64),
        aggregation: str = "max",
        pooling: str = "max",
        activation_fn: type[nn.Module] = nn.ReLU,
        n_critics: int = 2,
        normalize_images: bool = True,
        share_features_extractor: bool = False,
    ) -> None:
        super().__init__(observation_space, action_space, features_extractor=None, normalize_images=False)
        _, node_features, num_relations = graph_dims(observation_space, action_space)
        self.n_critics = n_critics
        self.share_features_extractor = False
        self.q_networks: list[GraphQNetwork] = []
        for idx in range(n_critics):
            q_net = GraphQNetwork(
                node_features, num_relations, encoder_dim, conv_dims, aggregation, pooling, activation_fn
            )
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)

    def forward(self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor) -> tuple[Tensor, ...]:
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions
        :return: one ``(B, 1)`` Q tensor per critic
        """
        graphs = as_graph_batch(obs)
        vertex_actions = gather_vertex_values(actions, graphs)
        # One network at a time: on CPU, stacked_q_forward over all critics (batched matmuls) was
        # measured slightly slower; the aggregation indices are shared through the cache anyway.
        return tuple(q_net(graphs, vertex_actions) for q_net in self.q_networks)

    def q1_forward(self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor) -> Tensor:
        """Q value of the first critic only (TD3's actor loss).

        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions
        :return: ``(B, 1)``
        """
        graphs = as_graph_batch(obs)
        return self.q_networks[0](graphs, gather_vertex_values(actions, graphs))


class GraphPolicy(TD3Policy):
    """TD3 policy with relational graph neural network actor and critics (Klimke et al. 2022).

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
    :param optimizer_kwargs: optimizer keyword arguments, excluding the learning rate
    :param n_critics: number of critic networks (TD3: 2)
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param features_extractor_class: not used (graphs go straight to the networks)
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param share_features_extractor: not used (nothing to share)
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
    ) -> None:
        graph_dims(observation_space, action_space)
        if net_arch is not None:
            raise ValueError(
                "GraphPolicy: net_arch is not used by graph networks; set encoder_dim and conv_dims instead"
            )
        if aggregation not in AGGREGATIONS:
            raise ValueError(f"GraphPolicy: aggregation must be one of {AGGREGATIONS}, got {aggregation!r}")
        if pooling not in POOLINGS:
            raise ValueError(f"GraphPolicy: pooling must be one of {tuple(POOLINGS)}, got {pooling!r}")
        conv_dims = [int(d) for d in conv_dims]
        if int(encoder_dim) < 1 or any(d < 1 for d in conv_dims):
            raise ValueError(
                f"GraphPolicy: encoder_dim and conv_dims must be positive, got {encoder_dim} and {conv_dims}"
            )
        # Read by make_actor / make_critic, which TD3Policy.__init__ calls.
        self.graph_kwargs = dict(
            encoder_dim=int(encoder_dim),
            conv_dims=conv_dims,
            aggregation=aggregation,
            activation_fn=activation_fn,
        )
        self.pooling = pooling
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
            optimizer_kwargs=optimizer_kwargs,
            n_critics=n_critics,
            share_features_extractor=share_features_extractor,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.pop("net_arch", None)
        data.update(self.graph_kwargs)
        data["pooling"] = self.pooling
        return data

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
