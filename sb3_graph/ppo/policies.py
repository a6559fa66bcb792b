"""Actor-critic graph policy for PPO and A2C: a per-vertex Gaussian and a value from the pooled graph.

The actor trunk gives each real vertex the mean of a Gaussian over its action; the standard
deviation is one learned, state-independent parameter shared by all vertices (SB3's
``log_std``). The log-probability and the entropy of a graph's action are sums over its real
vertices (:mod:`sb3_graph.common.distributions`). The critic trunk's vertex embeddings are pooled into
one row per graph and a linear head gives the value. Padded action slots are exactly 0, carry no
probability and never reach a loss.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import Tensor, nn

from sb3_graph.common.batching import GraphBatch, as_graph_batch, batch_to_padded, gather_vertex_values
from sb3_graph.common.distributions import gaussian_entropy, gaussian_log_prob, sum_per_graph
from sb3_graph.common.networks import GraphTrunk, graph_dims, graph_net_kwargs, pool_graphs


class GraphActorCriticPolicy(BasePolicy):
    """Graph actor-critic policy with SB3's ``ActorCriticPolicy`` interface (``forward``,
    ``evaluate_actions``, ``predict_values``), for :class:`sb3_graph.PPO` / :class:`sb3_graph.A2C`
    and for stock ``stable_baselines3.PPO(GraphActorCriticPolicy, env)`` (padded ``DictRolloutBuffer``).

    Actions are unbounded Gaussian samples, as in SB3's ``MlpPolicy``: SB3 clips them to the action
    space before the environment sees them and stores the unclipped ones. Use a symmetric action
    space such as ``Box(-1, 1, (max_nodes,))``.

    :param observation_space: graph observation space
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param lr_schedule: learning rate schedule
    :param encoder_dim: output size of the vertex encoder
    :param conv_dims: output sizes of the relational convolutions
    :param aggregation: aggregation over the in-neighbours of one relation: ``max``, ``mean``, ``sum``
    :param pooling: value pooling over a graph's vertices: ``max``, ``mean``, ``sum``
    :param activation_fn: activation function
    :param log_std_init: initial log standard deviation of every vertex's Gaussian
    :param share_trunk: one trunk for the actor and the value (False: two trunks, as SB3's separate
        ``pi`` and ``vf`` networks)
    :param ortho_init: orthogonal initialization of the heads (SB3's gains: 0.01 for the action
        mean, 1 for the value)
    :param use_sde: must be False (gSDE is not supported)
    :param optimizer_class: optimizer, ``torch.optim.Adam`` by default
    :param optimizer_kwargs: optimizer keyword arguments (SB3's default for Adam: ``eps=1e-5``)
    :param net_arch: not used by graph networks; accepted only as ``None``
    :param features_extractor_class: not used
    :param features_extractor_kwargs: not used
    :param normalize_images: not used
    :param use_edge_features: feed the space's edge features (if it has any) into every convolution
    """

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
        log_std_init: float = 0.0,
        share_trunk: bool = False,
        ortho_init: bool = True,
        use_sde: bool = False,
        optimizer_class: type[torch.optim.Optimizer] = torch.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        net_arch: Any = None,
        features_extractor_class: type = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        use_edge_features: bool = True,
    ) -> None:
        _, node_features, num_relations = graph_dims(observation_space, action_space)
        if use_sde:
            raise ValueError("GraphActorCriticPolicy: use_sde=True (gSDE) is not supported; use use_sde=False")
        self.graph_kwargs = graph_net_kwargs(
            observation_space,
            "GraphActorCriticPolicy",
            encoder_dim,
            conv_dims,
            aggregation,
            activation_fn,
            use_edge_features,
            net_arch=net_arch,
            pooling=pooling,
        )
        if optimizer_kwargs is None:
            optimizer_kwargs = {"eps": 1e-5} if optimizer_class is torch.optim.Adam else {}
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=False,
            squash_output=False,
        )
        self.pooling = pooling
        self.log_std_init = float(log_std_init)
        self.share_trunk = share_trunk
        self.ortho_init = ortho_init
        self.use_edge_features = use_edge_features
        self.pi_trunk = GraphTrunk(node_features, num_relations, **self.graph_kwargs)
        self.vf_trunk = self.pi_trunk if share_trunk else GraphTrunk(node_features, num_relations, **self.graph_kwargs)
        self.action_net = nn.Linear(self.pi_trunk.out_dim, 1)
        self.value_net = nn.Linear(self.vf_trunk.out_dim, 1)
        self.log_std = nn.Parameter(torch.full((1,), self.log_std_init))
        if ortho_init:
            for module, gain in ((self.action_net, 0.01), (self.value_net, 1.0)):
                nn.init.orthogonal_(module.weight, gain=gain)
                nn.init.zeros_(module.bias)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update({k: v for k, v in self.graph_kwargs.items() if k != "edge_dim"})
        data.update(
            lr_schedule=self._dummy_schedule,
            pooling=self.pooling,
            log_std_init=self.log_std_init,
            share_trunk=self.share_trunk,
            ortho_init=self.ortho_init,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            use_edge_features=self.use_edge_features,
        )
        return data

    def reset_noise(self, n_envs: int = 1) -> None:
        """No-op: gSDE is not supported."""

    def vertex_distribution(self, graphs: GraphBatch) -> tuple[Tensor, Tensor]:
        """``(N,)`` mean and ``(N,)`` log std of each real vertex's Gaussian."""
        mean = self.action_net(self.pi_trunk.embed(graphs)).squeeze(-1)
        return mean, self.log_std.expand_as(mean)

    def _values(self, graphs: GraphBatch, pi_embedding: Tensor | None = None) -> Tensor:
        h = pi_embedding if self.share_trunk and pi_embedding is not None else self.vf_trunk.embed(graphs)
        return self.value_net(pool_graphs(h, graphs, self.pooling))

    def forward(
        self, obs: GraphBatch | Mapping[str, Tensor], deterministic: bool = False
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Sample actions, with the values and log-probabilities (what SB3's rollout collection calls).

        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param deterministic: take the means
        :return: ``(B, max_nodes)`` actions (0 in padded slots), ``(B, 1)`` values, ``(B,)`` log-probabilities
        """
        graphs = as_graph_batch(obs)
        h = self.pi_trunk.embed(graphs)
        mean = self.action_net(h).squeeze(-1)
        log_std = self.log_std.expand_as(mean)
        actions = mean if deterministic else mean + torch.randn_like(mean) * torch.exp(log_std)
        log_prob = sum_per_graph(gaussian_log_prob(actions, mean, log_std), graphs)
        return batch_to_padded(actions, graphs), self._values(graphs, h), log_prob

    def evaluate_actions(
        self, obs: GraphBatch | Mapping[str, Tensor], actions: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Values, log-probabilities and entropies of given actions (PPO's and A2C's losses).

        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :param actions: ``(B, max_nodes)`` padded actions; padded slots are never read
        :return: ``(B, 1)`` values, ``(B,)`` log-probabilities and ``(B,)`` entropies, each summed
            over the graph's real vertices
        """
        graphs = as_graph_batch(obs)
        h = self.pi_trunk.embed(graphs)
        mean = self.action_net(h).squeeze(-1)
        log_std = self.log_std.expand_as(mean)
        vertex_actions = gather_vertex_values(actions, graphs).to(mean.dtype)
        log_prob = sum_per_graph(gaussian_log_prob(vertex_actions, mean, log_std), graphs)
        entropy = sum_per_graph(gaussian_entropy(log_std), graphs)
        return self._values(graphs, h), log_prob, entropy

    def predict_values(self, obs: GraphBatch | Mapping[str, Tensor]) -> Tensor:
        """
        :param obs: a :class:`GraphBatch` or a padded dictionary of tensors
        :return: ``(B, 1)`` values
        """
        return self._values(as_graph_batch(obs))

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> Tensor:
        return self(observation, deterministic)[0]  # type: ignore[arg-type]

    def get_std(self) -> Tensor:
        """The standard deviation shared by every vertex's Gaussian."""
        return torch.exp(self.log_std)
