"""The relational GNN pieces that every graph policy shares (Klimke et al., IEEE IV 2022).

- :class:`GraphTrunk`: a dense vertex encoder and relational convolutions, one embedding per vertex;
- :class:`GraphQNetwork` / :class:`GraphCritic`: Q(s, a) from each vertex's features joined with its
  action, pooled over the graph (the critics of TD3, DDPG, SAC; TQC's quantile critic and CrossQ's
  critic build on them);
- :func:`pool_graphs`: permutation-invariant pooling of vertex embeddings into one row per graph;
- :func:`graph_net_kwargs`: the checked network options (``encoder_dim``, ``conv_dims``,
  ``aggregation``, ``activation_fn``, ``use_edge_features``) that every graph policy accepts.

Observations arrive either as a :class:`~sb3_graph.common.batching.GraphBatch` (from the graph buffers)
or as SB3's padded dictionary of tensors (``predict``, ``DictReplayBuffer``); actions are always
padded ``(B, max_nodes)`` at this boundary.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from torch import Tensor, nn
from torch_geometric.nn import global_add_pool, global_max_pool, global_mean_pool

from sb3_graph.common.batching import GraphBatch, as_graph_batch, derived_indices, gather_vertex_values
from sb3_graph.common.layers import AGGREGATIONS, RelationalMaxConv, relational_conv, segment_max
from sb3_graph.common.spaces import edge_dims, graph_dims

POOLINGS = {"max": global_max_pool, "mean": global_mean_pool, "sum": global_add_pool}

__all__ = [
    "POOLINGS",
    "constant_parameters",
    "fast_optimizer_kwargs",
    "GraphCritic",
    "GraphQNetwork",
    "GraphTrunk",
    "graph_dims",
    "graph_net_kwargs",
    "pool_graphs",
    "stacked_q_forward",
    "stacked_trunk_forward",
]


def graph_net_kwargs(
    observation_space: spaces.Space,
    owner: str,
    encoder_dim: int = 64,
    conv_dims: Sequence[int] = (64, 64),
    aggregation: str = "max",
    activation_fn: type[nn.Module] = nn.ReLU,
    use_edge_features: bool = True,
    net_arch: Any = None,
    pooling: str | None = None,
) -> dict[str, Any]:
    """Check the network options of a graph policy and return the trunk's keyword arguments.

    :param observation_space: the graph observation space (its edge features size ``edge_dim``)
    :param owner: class name for the error messages
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over the in-neighbours of one relation
    :param activation_fn: activation after the encoder and after each convolution
    :param use_edge_features: feed the space's edge features (if any) into every convolution
    :param net_arch: must be ``None`` (SB3's MLP option has no meaning for graph networks)
    :param pooling: pooling over a graph's vertices, checked when given
    :return: ``encoder_dim``, ``conv_dims``, ``aggregation``, ``activation_fn``, ``edge_dim``
    :raises ValueError: naming the option
    """
    if net_arch is not None:
        raise ValueError(f"{owner}: net_arch is not used by graph networks; set encoder_dim and conv_dims instead")
    if aggregation not in AGGREGATIONS:
        raise ValueError(f"{owner}: aggregation must be one of {AGGREGATIONS}, got {aggregation!r}")
    if pooling is not None and pooling not in POOLINGS:
        raise ValueError(f"{owner}: pooling must be one of {tuple(POOLINGS)}, got {pooling!r}")
    conv_dims = [int(d) for d in conv_dims]
    if int(encoder_dim) < 1 or any(d < 1 for d in conv_dims):
        raise ValueError(f"{owner}: encoder_dim and conv_dims must be positive, got {encoder_dim} and {conv_dims}")
    return dict(
        encoder_dim=int(encoder_dim),
        conv_dims=conv_dims,
        aggregation=aggregation,
        activation_fn=activation_fn,
        edge_dim=edge_dims(observation_space) if use_edge_features else 0,
    )


def fast_optimizer_kwargs(
    optimizer_class: type[torch.optim.Optimizer], optimizer_kwargs: dict[str, Any] | None
) -> dict[str, Any]:
    """The optimizer keyword arguments of a graph policy: ``foreach=True`` for Adam and AdamW
    unless ``foreach``, ``fused``, ``differentiable`` or ``capturable`` is given.

    On CPU torch otherwise picks the per-tensor implementation, a Python loop of ~10 tensor
    operations per parameter tensor: ~0.8 ms per critic update of a default TD3 graph policy
    (20 tensors), against ~0.5 ms with ``foreach``, which computes the same updates bit for bit.
    (``fused=True`` takes ~0.15 ms, but its rounding differs by an ulp, which a max aggregation
    can turn into another winner within a few steps: an option, not the default.)

    :param optimizer_class: the policy's optimizer class
    :param optimizer_kwargs: the keyword arguments given (``None``: none)
    :return: a new dictionary
    """
    kwargs = dict(optimizer_kwargs or {})
    chosen = {"foreach", "fused", "differentiable", "capturable"} & set(kwargs)
    if optimizer_class in (torch.optim.Adam, torch.optim.AdamW) and not chosen:
        kwargs["foreach"] = True
    return kwargs


class GraphPolicyParameters:
    """Mixin of the off-policy graph policies: their saved constructor parameters are the graph
    network's (``graph_kwargs``, ``pooling``, ``use_edge_features``) in place of SB3's ``net_arch``.
    Put it before the SB3 policy class in the bases."""

    graph_kwargs: dict[str, Any]
    pooling: str
    use_edge_features: bool

    def _set_graph_kwargs(
        self,
        observation_space: spaces.Space,
        policy_name: str,
        encoder_dim: int,
        conv_dims: Sequence[int],
        aggregation: str,
        activation_fn: type[nn.Module],
        use_edge_features: bool,
        net_arch: Any,
        pooling: str,
    ) -> None:
        """Check the graph network's options and keep them (read by ``make_actor``/``make_critic``,
        which the SB3 policy's ``__init__`` calls: call this before it)."""
        self.graph_kwargs = graph_net_kwargs(
            observation_space,
            policy_name,
            encoder_dim,
            conv_dims,
            aggregation,
            activation_fn,
            use_edge_features,
            net_arch=net_arch,
            pooling=pooling,
        )
        self.pooling = pooling
        self.use_edge_features = use_edge_features

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        data.pop("net_arch", None)
        data.update({k: v for k, v in self.graph_kwargs.items() if k != "edge_dim"})
        data.update(pooling=self.pooling, use_edge_features=self.use_edge_features)
        return data


class GraphTrunk(nn.Module):
    """Vertex encoder (one dense layer shared by all vertices) followed by relational convolutions,
    each followed by the activation.

    :param in_dim: input features per vertex
    :param num_relations: number of edge types
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over the in-neighbours of one relation (``max``, ``mean``, ``sum``)
    :param activation_fn: activation after the encoder and after each convolution
    :param edge_dim: edge features per edge read by every convolution (0: none)
    """

    def __init__(
        self,
        in_dim: int,
        num_relations: int,
        encoder_dim: int = 64,
        conv_dims: Sequence[int] = (64, 64),
        aggregation: str = "max",
        activation_fn: type[nn.Module] = nn.ReLU,
        edge_dim: int = 0,
    ) -> None:
        super().__init__()
        self.encoder = nn.Linear(in_dim, encoder_dim)
        dims = [encoder_dim, *conv_dims]
        self.convs = nn.ModuleList(
            RelationalMaxConv(dims[i], dims[i + 1], num_relations, aggr=aggregation, edge_dim=edge_dim)
            for i in range(len(conv_dims))
        )
        self.activation = activation_fn()
        self.out_dim = dims[-1]
        self.edge_dim = edge_dim

    def forward(self, x: Tensor, edge_index: Tensor, edge_type: Tensor, edge_attr: Tensor | None = None) -> Tensor:
        """
        :param x: ``(N, in_dim)`` vertex features
        :param edge_index: ``(2, E)`` long
        :param edge_type: ``(E,)`` long
        :param edge_attr: ``(E, edge_dim)`` edge features (read only when ``edge_dim > 0``)
        :return: ``(N, out_dim)`` vertex embeddings
        """
        return stacked_trunk_forward([self], x, edge_index, edge_type, edge_attr)[0]

    def embed(self, graphs: GraphBatch, x: Tensor | None = None) -> Tensor:
        """``(N, out_dim)`` vertex embeddings of a batch (``x`` replaces ``graphs.x`` when given)."""
        return self(graphs.x if x is None else x, graphs.edge_index, graphs.edge_type, graphs.edge_attr)


def _activate(activation: nn.Module, h: Tensor) -> Tensor:
    # In place for ReLU: every h here is a fresh output that its producer's backward does not read.
    return h.relu_() if type(activation) is nn.ReLU else activation(h)


def stacked_trunk_forward(
    trunks: Sequence[GraphTrunk],
    x: Tensor,
    edge_index: Tensor,
    edge_type: Tensor,
    edge_attr: Tensor | None = None,
) -> Tensor:
    """Run ``K`` trunks of the same shape on the same graph batch at once (batched matmuls, one
    aggregation per layer for all of them); each output equals ``trunks[k](x, edge_index, edge_type)``.

    :param trunks: ``K`` trunks with equal dimensions, aggregation and activation
    :param x: ``(N, in_dim)`` vertex features, shared by all trunks
    :param edge_index: ``(2, E)`` long
    :param edge_type: ``(E,)`` long
    :param edge_attr: ``(E, edge_dim)`` edge features, read only when the trunks use them
    :return: ``(K, N, out_dim)`` vertex embeddings
    """
    first = trunks[0]
    edge_attr = edge_attr if first.edge_dim else None
    if len(trunks) == 1:  # 2-D tensors: see relational_conv
        h = _activate(first.activation, first.encoder(x))
        for conv in first.convs:
            h = _activate(first.activation, relational_conv([conv], h, edge_index, edge_type, edge_attr))
        return h.unsqueeze(0)
    weight = torch.stack([t.encoder.weight for t in trunks]).transpose(1, 2)
    bias = torch.stack([t.encoder.bias for t in trunks]).unsqueeze(1)
    h = _activate(first.activation, torch.baddbmm(bias, x.expand(len(trunks), -1, -1), weight))
    for layer in range(len(first.convs)):
        convs = [t.convs[layer] for t in trunks]
        h = _activate(first.activation, relational_conv(convs, h, edge_index, edge_type, edge_attr))
    return h


def _pool_index(batch: Tensor, num_graphs: int, copies: int) -> tuple[Tensor, int]:
    """Graph id of every vertex of ``copies`` stacked batches (copy ``k``: ids ``+ k * B``) and the
    number of non-empty graphs."""

    def compute() -> tuple[Tensor, int]:
        offsets = torch.arange(copies, device=batch.device).unsqueeze(-1) * num_graphs
        nonempty = int(torch.count_nonzero(torch.bincount(batch, minlength=num_graphs)))
        return (batch + offsets).view(-1), nonempty * copies

    return derived_indices.get((batch,), ("pool", num_graphs, copies), compute)


def pool_graphs(h: Tensor, graphs: GraphBatch, pooling: str, copies: int = 1) -> Tensor:
    """Pool vertex embeddings into one row per graph (an empty graph pools to 0).

    :param h: ``(copies * N, C)`` embeddings of ``copies`` stacked networks on the same batch
    :param graphs: the batch
    :param pooling: ``max``, ``mean`` or ``sum``
    :param copies: number of stacked networks
    :return: ``(copies * B, C)``
    """
    index, nonempty = _pool_index(graphs.batch, graphs.num_graphs, copies)
    if pooling == "max":
        return segment_max(h, None, index, copies * graphs.num_graphs, nonempty)
    return POOLINGS[pooling](h, index, copies * graphs.num_graphs)


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
    :param edge_dim: edge features read by the convolutions (0: none)
    :param n_outputs: outputs of the head (1 Q value; TQC: the quantiles)
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
        edge_dim: int = 0,
        n_outputs: int = 1,
    ) -> None:
        super().__init__()
        self.trunk = GraphTrunk(
            node_features + 1, num_relations, encoder_dim, conv_dims, aggregation, activation_fn, edge_dim
        )
        self.pooling = pooling
        self.pool = POOLINGS[pooling]
        self.head = nn.Linear(self.trunk.out_dim, n_outputs)

    def forward(self, graphs: GraphBatch, vertex_actions: Tensor) -> Tensor:
        """
        :param graphs: the batch
        :param vertex_actions: ``(N,)`` action of each real vertex
        :return: ``(B, n_outputs)`` Q values (or quantiles)
        """
        return stacked_q_forward([self], graphs, vertex_actions)[0]


def stacked_q_forward(q_networks: Sequence[GraphQNetwork], graphs: GraphBatch, vertex_actions: Tensor) -> Tensor:
    """Run ``K`` Q networks of the same shape on the same batch at once; ``out[k]`` equals
    ``q_networks[k](graphs, vertex_actions)``.

    :param q_networks: ``K`` networks with equal dimensions, aggregation, pooling and activation
    :param graphs: the batch
    :param vertex_actions: ``(N,)`` action of each real vertex
    :return: ``(K, B, n_outputs)`` Q values
    """
    copies, num_graphs = len(q_networks), graphs.num_graphs
    x = torch.cat((graphs.x, vertex_actions.unsqueeze(-1).to(graphs.x.dtype)), dim=-1)
    h = stacked_trunk_forward([q.trunk for q in q_networks], x, graphs.edge_index, graphs.edge_type, graphs.edge_attr)
    h = h.view(copies * h.size(1), h.size(2))
    pooled = pool_graphs(h, graphs, q_networks[0].pooling, copies).view(copies, num_graphs, -1)
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
    :param edge_dim: edge features read by the convolutions (0: none)
    :param n_outputs: outputs of each network's head (1: a Q value)

    While :attr:`policy_loss_without_weight_gradients` is set (the graph algorithms set it for the
    duration of their ``train``, see :class:`~sb3_graph.common.algorithm.GraphAlgorithmMixin`), a call on
    actions that carry a gradient (the actor's: a policy loss) treats the critics' own parameters
    as constants: the actor's gradients are the same, and the critics' weight gradients, which the
    algorithm discards (its next critic update starts with ``zero_grad``), are not computed.
    """

    #: In a call on actions that require a gradient, leave the critics' parameters out of autograd.
    policy_loss_without_weight_gradients: bool = False

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
        edge_dim: int = 0,
        n_outputs: int = 1,
    ) -> None:
        super().__init__(observation_space, action_space, features_extractor=None, normalize_images=False)
        _, node_features, num_relations = graph_dims(observation_space, action_space)
        self.n_critics = n_critics
        self.share_features_extractor = False
        self.q_networks: list[GraphQNetwork] = []
        for idx in range(n_critics):
            q_net = GraphQNetwork(
                node_features,
                num_relations,
                encoder_dim,
                conv_dims,
                aggregation,
                pooling,
                activation_fn,
                edge_dim=edge_dim,
                n_outputs=n_outputs,
            )
            self.add_module(f"qf{idx}", q_net)
            self.q_networks.append(q_net)

    def forward(self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor) -> tuple[Tensor, ...]:
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions
        :return: one ``(B, n_outputs)`` tensor per critic
        """
        graphs = as_graph_batch(obs)
        vertex_actions = gather_vertex_values(actions, graphs)
        # One network at a time: on CPU, stacked_q_forward over all critics (batched matmuls) was
        # measured slightly slower; the aggregation indices are shared through the cache anyway.
        with self._policy_loss_scope(self.q_networks, actions):
            return tuple(q_net(graphs, vertex_actions) for q_net in self.q_networks)

    def q1_forward(self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor) -> Tensor:
        """Q value of the first critic only (TD3's actor loss).

        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions
        :return: ``(B, n_outputs)``
        """
        graphs = as_graph_batch(obs)
        with self._policy_loss_scope(self.q_networks[:1], actions):
            return self.q_networks[0](graphs, gather_vertex_values(actions, graphs))

    def _policy_loss_scope(self, networks: Sequence[nn.Module], actions: Tensor) -> contextlib.AbstractContextManager:
        """Parameters of ``networks`` out of autograd for a policy loss (see the class docstring),
        else nothing."""
        if self.policy_loss_without_weight_gradients and actions.requires_grad and torch.is_grad_enabled():
            return constant_parameters(networks)
        return contextlib.nullcontext()


@contextlib.contextmanager
def constant_parameters(modules: Sequence[nn.Module]) -> Iterator[None]:
    """Within the block, the parameters of ``modules`` that require gradients do not: operations
    record no gradient path to them (autograd neither computes nor accumulates their gradients),
    while gradients still flow through the modules to their inputs.

    :param modules: the modules whose parameters are constants in the block
    """
    parameters = [p for module in modules for p in module.parameters() if p.requires_grad]
    for parameter in parameters:
        parameter.requires_grad_(False)
    try:
        yield
    finally:
        for parameter in parameters:
            parameter.requires_grad_(True)
