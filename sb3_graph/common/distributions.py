"""Per-vertex Gaussian action distributions over ragged graph batches.

A graph with ``n`` real vertices takes an ``n``-dimensional action: one independent Gaussian per
real vertex, the same per-vertex formulas as SB3's ``DiagGaussianDistribution`` (PPO, A2C) and
``SquashedDiagGaussianDistribution`` (SAC, TQC, CrossQ). The log-probability (and entropy) of a
graph's action is the *sum over its real vertices*: padded slots have no distribution, add nothing
and receive no gradient. For a graph of ``n`` vertices the result equals SB3's distribution of
dimension ``n`` on the real vertices' actions (``tests/test_distributions.py`` checks it graph by
graph).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from sb3_graph.common.batching import GraphBatch

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # SB3's bounds for SAC's state-dependent log std
SQUASH_EPSILON = 1e-6  # SB3's SquashedDiagGaussianDistribution epsilon
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def sum_per_graph(values: Tensor, graphs: GraphBatch) -> Tensor:
    """``(B,)`` sum of per-vertex ``values`` ``(N,)`` over each graph's real vertices (0 for an
    empty graph)."""
    return values.new_zeros(graphs.num_graphs).index_add(0, graphs.batch, values)


def gaussian_log_prob(actions: Tensor, mean: Tensor, log_std: Tensor) -> Tensor:
    """Per-vertex log density of ``N(mean, exp(log_std)^2)`` at ``actions`` (all ``(N,)``)."""
    return -0.5 * ((actions - mean) * torch.exp(-log_std)) ** 2 - log_std - _HALF_LOG_2PI


def gaussian_entropy(log_std: Tensor) -> Tensor:
    """Per-vertex entropy of a Gaussian with ``log_std``."""
    return 0.5 + _HALF_LOG_2PI + log_std


def squashed_sample(mean: Tensor, log_std: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor]:
    """Sample ``tanh(u)``, ``u ~ N(mean, std^2)`` per vertex, with its log-probability (tanh's change
    of variables with SB3's epsilon: ``log N(u) - log(1 - tanh(u)^2 + 1e-6)``).

    :param mean: ``(N,)`` means of the pre-squash Gaussian
    :param log_std: ``(N,)`` log standard deviations
    :param deterministic: take ``u = mean``
    :return: ``(N,)`` actions in ``(-1, 1)`` and ``(N,)`` per-vertex log-probabilities
    """
    gaussian = mean if deterministic else mean + torch.randn_like(mean) * torch.exp(log_std)
    actions = torch.tanh(gaussian)
    log_prob = gaussian_log_prob(gaussian, mean, log_std) - torch.log(1.0 - actions**2 + SQUASH_EPSILON)
    return actions, log_prob
