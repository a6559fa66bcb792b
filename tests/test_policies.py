"""GraphPolicy: permutation symmetry, direction and relation sensitivity, padded slots ignored."""

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.utils import obs_as_tensor
from torch_geometric.nn import global_max_pool

from sb3_graph import GraphPolicy, GraphSpace
from sb3_graph.common.batching import gather_vertex_values, padded_to_batch
from sb3_graph.policies import stacked_q_forward

torch.set_num_threads(1)

SPACE = GraphSpace(max_nodes=6, node_features=3, max_edges=12, num_relations=2, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (6,), np.float32)


def make_policy(**kwargs) -> GraphPolicy:
    torch.manual_seed(0)
    return GraphPolicy(SPACE, ACTIONS, lambda _: 1e-3, **kwargs)


def as_tensors(*graphs):
    return obs_as_tensor({k: np.stack([g[k] for g in graphs]) for k in graphs[0]}, "cpu")


def graph(n=5, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3)).astype(np.float32)
    edge_index = np.array([[0, 1, 2, 3, 4, 0, 2], [1, 2, 3, 4, 0, 2, 4]])
    edge_type = np.array([0, 1, 0, 1, 0, 0, 1])
    keep = edge_index.max(axis=0) < n
    return x, edge_index[:, keep], edge_type[keep]


@pytest.mark.parametrize("pooling", ["max", "mean", "sum"])
def test_permutation_equivariance_and_invariance(pooling):
    policy = make_policy(pooling=pooling)
    x, edge_index, edge_type = graph()
    perm = np.array([3, 0, 4, 1, 2])  # new vertex k is old vertex perm[k]
    inverse = np.argsort(perm)
    obs = SPACE.encode(x, edge_index, edge_type)
    permuted = SPACE.encode(x[perm], inverse[edge_index], edge_type)
    with torch.no_grad():
        actions = policy.actor(as_tensors(obs))
        permuted_actions = policy.actor(as_tensors(permuted))
        torch.testing.assert_close(permuted_actions[0, :5], actions[0, :5][perm])
        some_actions = torch.rand(1, 6) * 2 - 1
        permuted_input = some_actions.clone()
        permuted_input[0, :5] = some_actions[0, perm]
        for q, q_permuted in zip(
            policy.critic(as_tensors(obs), some_actions), policy.critic(as_tensors(permuted), permuted_input)
        ):
            torch.testing.assert_close(q, q_permuted)


def vertex_outputs(policy, x, edge_index, edge_type):
    with torch.no_grad():
        return policy.actor.vertex_actions(
            padded_to_batch(as_tensors(SPACE.encode(x, edge_index, edge_type)))
        )


def test_direction_and_relation():
    policy = make_policy()
    x = np.array([[1.0, -0.5, 0.3], [-0.2, 0.4, 0.9]], np.float32)
    none = vertex_outputs(policy, x, None, None)
    forward = vertex_outputs(policy, x, np.array([[0], [1]]), np.array([0]))
    # A message along 0 -> 1 changes the target's output, not the source's.
    assert forward[0] == pytest.approx(none[0].item(), abs=1e-7)
    assert abs(forward[1] - none[1]) > 1e-5
    swapped = vertex_outputs(policy, x, np.array([[0], [1]]), np.array([1]))
    assert abs(swapped[1] - forward[1]) > 1e-5
    reverse = vertex_outputs(policy, x, np.array([[1], [0]]), np.array([0]))
    assert reverse[1] == pytest.approx(none[1].item(), abs=1e-7)


def test_padded_slots_cannot_change_q():
    policy = make_policy()
    obs = SPACE.encode(*graph(n=3))
    garbage = {k: v.copy() for k, v in obs.items()}
    garbage["x"][3:] = 7.0  # padded feature rows
    garbage["edge_index"][:, 3:] = 5  # padded edge slots pointing at padded vertices
    garbage["edge_type"][3:] = 1
    actions = torch.rand(1, 6) * 2 - 1
    noisy = actions.clone()
    noisy[0, 3:] = torch.randn(3) * 10  # padded action slots, e.g. TD3's smoothing noise
    noisy.requires_grad_(True)
    with torch.no_grad():
        reference = policy.critic(as_tensors(obs), actions)
    result = policy.critic(as_tensors(garbage), noisy)
    for q, q_ref in zip(result, reference):
        torch.testing.assert_close(q, q_ref)
    sum(result).sum().backward()
    assert torch.all(noisy.grad[0, 3:] == 0) and torch.any(noisy.grad[0, :3] != 0)
    with torch.no_grad():
        torch.testing.assert_close(policy.actor(as_tensors(garbage)), policy.actor(as_tensors(obs)))


def test_padded_actions_are_zero_and_empty_graph_is_finite():
    policy = make_policy()
    obs = SPACE.encode(*graph(n=3))
    empty = SPACE.encode(np.zeros((0, 3), np.float32))
    with torch.no_grad():
        actions = policy.actor(as_tensors(obs, empty))
        assert torch.all(actions[0, 3:] == 0) and torch.all(actions[1] == 0)
        assert torch.all(actions[0, :3].abs() < 1) and torch.all(actions[0, :3] != 0)
        for q in policy.critic(as_tensors(obs, empty), actions):
            assert q.shape == (2, 1) and torch.all(torch.isfinite(q))
    predicted, _ = policy.predict(empty, deterministic=True)
    assert predicted.shape == (6,) and np.all(predicted == 0)


def test_batched_equals_single():
    policy = make_policy()
    graphs = [SPACE.encode(*graph(n=n, seed=n)) for n in (5, 2, 4)]
    with torch.no_grad():
        batched = policy.actor(as_tensors(*graphs))
        for i, g in enumerate(graphs):
            torch.testing.assert_close(batched[i], policy.actor(as_tensors(g))[0])


def test_options_and_errors():
    policy = make_policy(encoder_dim=16, conv_dims=[8, 8, 4], aggregation="mean", pooling="sum", n_critics=3)
    assert len(policy.critic.q_networks) == 3
    assert len(policy.actor.trunk.convs) == 3 and policy.actor.trunk.out_dim == 4
    with pytest.raises(ValueError, match="pooling"):
        make_policy(pooling="median")
    with pytest.raises(ValueError, match="aggregation"):
        make_policy(aggregation="min")
    with pytest.raises(ValueError, match="net_arch"):
        make_policy(net_arch=[64, 64])
    with pytest.raises(ValueError, match="action_space"):
        GraphPolicy(SPACE, spaces.Box(-1, 1, (5,), np.float32), lambda _: 1e-3)
    with pytest.raises(ValueError, match="observation_space"):
        GraphPolicy(spaces.Box(-1, 1, (6,)), ACTIONS, lambda _: 1e-3)


def test_critic_matches_reference_composition_and_stacked_forward():
    # Each critic = head(PyG max pool(trunk(x ++ action))); the stacked pass over all critics gives
    # the same values and gradients; q1_forward is the first critic alone.
    policy = make_policy(n_critics=3)
    graphs = [SPACE.encode(*graph(n=n, seed=n)) for n in (5, 2, 4)]
    graphs.append(SPACE.encode(np.zeros((0, 3), np.float32)))  # an empty graph pools to 0
    obs = as_tensors(*graphs)
    batch = padded_to_batch(obs)
    actions = (torch.rand(4, 6) * 2 - 1).requires_grad_(True)
    critic = policy.critic
    q_values = critic(obs, actions)
    vertex_actions = gather_vertex_values(actions, batch)
    x = torch.cat((batch.x, vertex_actions.unsqueeze(-1)), dim=-1)
    reference = [
        q.head(global_max_pool(q.trunk(x, batch.edge_index, batch.edge_type), batch.batch, batch.num_graphs))
        for q in critic.q_networks
    ]
    stacked = stacked_q_forward(critic.q_networks, batch, vertex_actions)
    assert len(q_values) == 3
    for k in range(3):
        torch.testing.assert_close(q_values[k], reference[k])
        torch.testing.assert_close(stacked[k], reference[k])
    torch.testing.assert_close(critic.q1_forward(obs, actions), q_values[0])
    parameters = [actions, *critic.parameters()]
    grads = torch.autograd.grad(sum(q.sum() for q in q_values), parameters)
    stacked_grads = torch.autograd.grad(stacked.sum(), parameters)
    for a, b in zip(grads, stacked_grads, strict=True):
        torch.testing.assert_close(a, b)
