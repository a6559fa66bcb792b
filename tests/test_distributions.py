"""Per-vertex Gaussians: a graph's log-probability and entropy are sums over its real vertices and
equal SB3's distributions of dimension n, graph by graph."""

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution, SquashedDiagGaussianDistribution
from stable_baselines3.common.utils import obs_as_tensor

from sb3_graph import GraphActorCriticPolicy, GraphSACPolicy, GraphSpace
from sb3_graph.common.batching import padded_to_batch

torch.set_num_threads(1)

SPACE = GraphSpace(max_nodes=7, node_features=3, max_edges=20, num_relations=2, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (7,), np.float32)
SIZES = (5, 0, 1, 7, 3)  # graphs of different sizes, an empty one included


def graphs():
    rng = np.random.default_rng(0)
    out = []
    for n in SIZES:
        e = 2 * n if n > 1 else 0
        src = rng.integers(0, max(n, 1), e)
        dst = (src + rng.integers(1, max(n, 2), e)) % max(n, 1)
        out.append(SPACE.encode(rng.standard_normal((n, 3)), np.stack([src, dst]), rng.integers(0, 2, e)))
    return obs_as_tensor({k: np.stack([g[k] for g in out]) for k in out[0]}, "cpu")


def test_squashed_log_prob_equals_sb3_per_graph():
    torch.manual_seed(0)
    actor = GraphSACPolicy(SPACE, ACTIONS, lambda _: 1e-3).actor
    obs = graphs()
    torch.manual_seed(1)
    actions, log_prob = actor.action_log_prob(obs)
    assert actions.shape == (len(SIZES), 7) and log_prob.shape == (len(SIZES),)
    mean, log_std = actor.vertex_distribution(padded_to_batch(obs))
    start = 0
    for b, n in enumerate(SIZES):
        assert torch.all(actions[b, n:] == 0)  # padded slots: no action
        if n == 0:
            assert log_prob[b] == 0  # an empty graph has probability 1
            continue
        dist = SquashedDiagGaussianDistribution(n).proba_distribution(
            mean[start : start + n], log_std[start : start + n]
        )
        # SB3's formula over the n real vertices (gaussian actions recovered by atanh).
        expected = dist.log_prob(actions[b, :n].unsqueeze(0), torch.atanh(actions[b, :n]).unsqueeze(0))
        torch.testing.assert_close(log_prob[b], expected[0], rtol=1e-4, atol=1e-4)
        start += n
    # Padded slots get no gradient, real vertices do.
    log_prob.sum().backward()
    assert all(p.grad is not None for p in actor.parameters() if p.requires_grad)


def test_gaussian_log_prob_and_entropy_equal_sb3_per_graph():
    torch.manual_seed(0)
    policy = GraphActorCriticPolicy(SPACE, ACTIONS, lambda _: 1e-3, log_std_init=-0.5)
    obs = graphs()
    actions = torch.rand(len(SIZES), 7) * 2 - 1
    noisy = actions.clone()
    noisy[:, :] = torch.where(torch.arange(7) < torch.tensor(SIZES)[:, None], actions, torch.randn(len(SIZES), 7) * 9)
    values, log_prob, entropy = policy.evaluate_actions(obs, noisy)
    assert values.shape == (len(SIZES), 1) and log_prob.shape == entropy.shape == (len(SIZES),)
    mean, log_std = policy.vertex_distribution(padded_to_batch(obs))
    start = 0
    for b, n in enumerate(SIZES):
        if n == 0:
            assert log_prob[b] == 0 and entropy[b] == 0
            continue
        dist = DiagGaussianDistribution(n)
        dist.proba_distribution(mean[start : start + n], log_std[start : start + n])
        torch.testing.assert_close(log_prob[b], dist.log_prob(actions[b, :n]))
        torch.testing.assert_close(entropy[b], dist.entropy())
        start += n
    # The actions SB3's rollout collection stores come back with their own log-probabilities.
    sampled, _, sampled_log_prob = policy(obs)
    torch.testing.assert_close(policy.evaluate_actions(obs, sampled)[1], sampled_log_prob)
    assert torch.all(sampled[torch.arange(7) >= torch.tensor(SIZES)[:, None]] == 0)


@pytest.mark.parametrize("share_trunk", [False, True])
def test_value_is_permutation_invariant_and_batched_equals_single(share_trunk):
    torch.manual_seed(0)
    policy = GraphActorCriticPolicy(SPACE, ACTIONS, lambda _: 1e-3, share_trunk=share_trunk, pooling="mean")
    rng = np.random.default_rng(3)
    x = rng.standard_normal((4, 3))
    edge_index, edge_type = np.array([[0, 1, 2], [1, 2, 3]]), np.array([0, 1, 0])
    perm = np.array([2, 0, 3, 1])
    single = [SPACE.encode(x, edge_index, edge_type), SPACE.encode(x[perm], np.argsort(perm)[edge_index], edge_type)]
    tensors = obs_as_tensor({k: np.stack([g[k] for g in single]) for k in single[0]}, "cpu")
    with torch.no_grad():
        values = policy.predict_values(tensors)
        torch.testing.assert_close(values[0], values[1])
        batched = policy.predict_values(graphs())
        for b in range(len(SIZES)):
            one = {k: v[b : b + 1] for k, v in graphs().items()}
            torch.testing.assert_close(batched[b], policy.predict_values(one)[0])
