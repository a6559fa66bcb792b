"""CrossQ policy (sb3-contrib) with the graph SAC actor and batch-renormalized graph critics.

CrossQ drops target networks and instead normalizes the critic's layers with batch
renormalization over the *joint* batch of observations and next observations
(``torch.cat([obs, next_obs])``; :class:`~sb3_graph.common.batching.GraphBatch` concatenates as a disjoint
union, so sb3-contrib's ``CrossQ.train`` runs unchanged).

Where batch renormalization meets ragged batches:

- The vertex-level layers (before the encoder and before each relational convolution) see one row
  per *real* vertex of the joint batch. Padded slots never enter the statistics (in a padded MLP
  they would, as rows of zeros), but a graph weighs in them by its vertex count: large graphs
  dominate the running means, and the statistics follow the distribution of vertices, not of
  graphs. The layer after pooling sees one row per graph, as CrossQ's MLP critic does.
- A batch with fewer than two rows (e.g. only empty graphs) is normalized with the running
  statistics and does not update them (a variance needs two rows).
- The graph actor has no batch renormalization (CrossQ's MLP actor has); only the critic has.
- Stock ``sb3_contrib.CrossQ(GraphCrossQPolicy, env)`` needs
  ``replay_buffer_class=GraphReplayBuffer``: with SB3's padded ``DictReplayBuffer`` the
  observations are dictionaries, which ``torch.cat`` cannot join. :class:`sb3_graph.CrossQ` uses
  the graph buffer by default.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from sb3_contrib.common.torch_layers import BatchRenorm1d
from sb3_contrib.crossq.policies import CrossQPolicy
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import Schedule
from torch import Tensor, nn

from sb3_graph.common.batching import GraphBatch, as_graph_batch, gather_vertex_values
from sb3_graph.common.layers import relational_conv
from sb3_graph.common.networks import GraphPolicyParameters, GraphTrunk, _activate, graph_dims, pool_graphs
from sb3_graph.sac.policies import GraphSACActor, _no_sde


def _renorm(norm: nn.Module, h: Tensor) -> Tensor:
    if isinstance(norm, BatchRenorm1d) and norm.training and h.size(0) < 2:
        norm.train(False)  # too few rows for batch statistics: running statistics, no update
        try:
            return norm(h)
        finally:
            norm.train(True)
    return norm(h)


class BatchRenormGraphQNetwork(nn.Module):
    """A graph Q network with batch renormalization before every linear map: the vertex encoder,
    each relational convolution (over real-vertex rows) and the head (over pooled graph rows).

    :param node_features: features per vertex (the action is appended)
    :param num_relations: number of edge types
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output size of each relational convolution
    :param aggregation: aggregation over in-neighbours of one relation
    :param pooling: ``max``, ``mean`` or ``sum`` over a graph's vertices
    :param activation_fn: activation function
    :param edge_dim: edge features read by the convolutions (0: none)
    :param batch_norm: use batch renormalization (False: identity layers)
    :param batch_norm_momentum: rate of the running statistics
    :param batch_norm_eps: added to the variance
    :param renorm_warmup_steps: steps of plain batch normalization before the running statistics are used
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
        batch_norm: bool = True,
        batch_norm_momentum: float = 0.01,
        batch_norm_eps: float = 0.001,
        renorm_warmup_steps: int = 100_000,
    ) -> None:
        super().__init__()
        self.trunk = GraphTrunk(
            node_features + 1, num_relations, encoder_dim, conv_dims, aggregation, activation_fn, edge_dim
        )

        def norm(dim: int) -> nn.Module:
            if not batch_norm:
                return nn.Identity()
            return BatchRenorm1d(
                dim, eps=batch_norm_eps, momentum=batch_norm_momentum, warmup_steps=renorm_warmup_steps
            )

        self.vertex_norms = nn.ModuleList(norm(d) for d in [node_features + 1, encoder_dim, *conv_dims[:-1]])
        self.graph_norm = norm(self.trunk.out_dim)
        self.pooling = pooling
        self.head = nn.Linear(self.trunk.out_dim, 1)

    def forward(self, graphs: GraphBatch, vertex_actions: Tensor) -> Tensor:
        """
        :param graphs: the batch
        :param vertex_actions: ``(N,)`` action of each real vertex
        :return: ``(B, 1)`` Q values
        """
        trunk = self.trunk
        h = torch.cat((graphs.x, vertex_actions.unsqueeze(-1).to(graphs.x.dtype)), dim=-1)
        h = _activate(trunk.activation, trunk.encoder(_renorm(self.vertex_norms[0], h)))
        edge_attr = graphs.edge_attr if trunk.edge_dim else None
        for conv, norm in zip(trunk.convs, self.vertex_norms[1:]):
            h = relational_conv([conv], _renorm(norm, h), graphs.edge_index, graphs.edge_type, edge_attr)
            h = _activate(trunk.activation, h)
        return self.head(_renorm(self.graph_norm, pool_graphs(h, graphs, self.pooling)))


class GraphCrossQCritic(BaseModel):
    """``n_critics`` batch-renormalized graph Q networks with sb3-contrib's ``CrossQCritic`` interface.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param n_critics: number of critic networks
    :param pooling: pooling over a graph's vertices
    :param batch_norm: use batch renormalization
    :param batch_norm_momentum: rate of the running statistics
    :param batch_norm_eps: added to the variance
    :param renorm_warmup_steps: steps of plain batch normalization before the running statistics are used
    :param kwargs: the trunk options (``encoder_dim``, ``conv_dims``, ``aggregation``,
        ``activation_fn``, ``edge_dim``)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        n_critics: int = 2,
        pooling: str = "max",
        batch_norm: bool = True,
        batch_norm_momentum: float = 0.01,
        batch_norm_eps: float = 0.001,
        renorm_warmup_steps: int = 100_000,
        **kwargs: Any,
    ) -> None:
        super().__init__(observation_space, action_space, features_extractor=None, normalize_images=False)
        _, node_features, num_relations = graph_dims(observation_space, action_space)
        self.n_critics = n_critics
        self.share_features_extractor = False
        self.q_networks: list[BatchRenormGraphQNetwork] = []
        for idx in range(n_critics):
            q_net = BatchRenormGraphQNetwork(
                node_features,
                num_relations,
                kwargs["encoder_dim"],
                kwargs["conv_dims"],
                kwargs["aggregation"],
                pooling,
                kwargs["activation_fn"],
                edge_dim=kwargs.get("edge_dim", 0),
                batch_norm=batch_norm,
                batch_norm_momentum=batch_norm_momentum,
                batch_norm_eps=batch_norm_eps,
                renorm_warmup_steps=renorm_warmup_steps,
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
        return tuple(q_net(graphs, vertex_actions) for q_net in self.q_networks)

    def set_bn_training_mode(self, mode: bool) -> None:
        """Whether the batch renormalization layers use and update batch statistics.

        :param mode: training mode of those layers
        """
        for module in self.modules():
            if isinstance(module, BatchRenorm1d):
                module.train(mode)


class GraphCrossQPolicy(GraphPolicyParameters, CrossQPolicy):
    """CrossQ policy (sb3-contrib) with the graph actor of :class:`~sb3_graph.GraphSACPolicy` and
    :class:`GraphCrossQCritic` critics; see the module docstring for how batch renormalization
    treats ragged batches.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param lr_schedule: learning rate schedule
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output sizes of the relational convolutions
    :param aggregation: aggregation over the in-neighbours of one relation: ``max``, ``mean``, ``sum``
    :param pooling: critic pooling over a graph's vertices: ``max``, ``mean``, ``sum``
    :param activation_fn: activation function
    :param batch_norm: batch renormalization in the critics
    :param batch_norm_momentum: rate of the running statistics
    :param batch_norm_eps: added to the variance
    :param renorm_warmup_steps: steps of plain batch normalization before the running statistics are used
    :param use_sde: must be False (gSDE is not supported)
    :param log_std_init: unused, kept for the signature
    :param use_expln: unused, kept for the signature
    :param clip_mean: unused, kept for the signature
    :param features_extractor_class: not used
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param optimizer_class: optimizer, ``torch.optim.Adam`` by default
    :param optimizer_kwargs: optimizer keyword arguments (CrossQ's default: Adam ``betas=(0.5, 0.999)``)
    :param n_critics: number of critic networks
    :param share_features_extractor: not used
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param use_edge_features: feed the space's edge features (if it has any) into every convolution
    """

    actor: GraphSACActor  # type: ignore[assignment]
    critic: GraphCrossQCritic  # type: ignore[assignment]

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
        batch_norm: bool = True,
        batch_norm_momentum: float = 0.01,
        batch_norm_eps: float = 0.001,
        renorm_warmup_steps: int = 100_000,
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
        _no_sde(use_sde, "GraphCrossQPolicy")
        self._set_graph_kwargs(
            observation_space, "GraphCrossQPolicy", encoder_dim, conv_dims, aggregation, activation_fn,
            use_edge_features, net_arch, pooling,
        )  # fmt: skip
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[],
            activation_fn=activation_fn,
            batch_norm=batch_norm,
            batch_norm_momentum=batch_norm_momentum,
            batch_norm_eps=batch_norm_eps,
            renorm_warmup_steps=renorm_warmup_steps,
            use_sde=False,
            log_std_init=log_std_init,
            use_expln=use_expln,
            clip_mean=clip_mean,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            n_critics=n_critics,
            share_features_extractor=False,
        )

    def make_actor(self, features_extractor: Any = None) -> GraphSACActor:  # type: ignore[override]
        return GraphSACActor(self.observation_space, self.action_space, **self.graph_kwargs).to(self.device)

    def make_critic(self, features_extractor: Any = None) -> GraphCrossQCritic:  # type: ignore[override]
        return GraphCrossQCritic(
            self.observation_space,
            self.action_space,
            n_critics=self.critic_kwargs["n_critics"],
            pooling=self.pooling,
            **self.batch_norm_params,
            **self.graph_kwargs,
        ).to(self.device)
