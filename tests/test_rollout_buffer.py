"""GraphRolloutBuffer: the minibatches, returns and advantages of SB3's DictRolloutBuffer, stored ragged."""

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import DictRolloutBuffer

from sb3_graph import GraphRolloutBuffer, GraphSpace
from sb3_graph.common.batching import GraphBatch, padded_to_batch

torch.set_num_threads(1)

SPACE = GraphSpace(max_nodes=7, node_features=2, max_edges=20, num_relations=3, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (7,), np.float32)


def fill(buffers, n_steps: int, n_envs: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(n_steps):
        graphs = [SPACE.sample() for _ in range(n_envs)]
        obs = {k: np.stack([g[k] for g in graphs]) for k in graphs[0]}
        action = rng.standard_normal((n_envs, 7)).astype(np.float32)
        action[obs["node_mask"] == 0] = 0.0  # the graph policies act on real vertices only
        reward = rng.standard_normal(n_envs).astype(np.float32)
        starts = rng.random(n_envs) < 0.2
        value, log_prob = torch.randn(n_envs, 1), torch.randn(n_envs)
        for buffer in buffers:
            buffer.add(obs, action, reward, starts, value, log_prob)
    for buffer in buffers:
        buffer.compute_returns_and_advantage(torch.tensor([[0.3]] * n_envs), np.array([False] * n_envs))


@pytest.mark.parametrize(("n_steps", "n_envs", "batch_size"), [(16, 1, 5), (8, 3, 6), (6, 2, None)])
def test_same_minibatches_as_dict_rollout_buffer(n_steps, n_envs, batch_size):
    ours = GraphRolloutBuffer(n_steps, SPACE, ACTIONS, device="cpu", gae_lambda=0.9, gamma=0.95, n_envs=n_envs)
    reference = DictRolloutBuffer(n_steps, SPACE, ACTIONS, device="cpu", gae_lambda=0.9, gamma=0.95, n_envs=n_envs)
    fill([ours, reference], n_steps, n_envs)
    np.testing.assert_allclose(ours.advantages, reference.advantages)
    for epoch in range(2):  # the second pass reuses the flattened arrays, as SB3's does
        np.random.seed(epoch)  # noqa: NPY002 (SB3 shuffles with the global generator)
        a = list(ours.get(batch_size))
        np.random.seed(epoch)  # noqa: NPY002
        b = list(reference.get(batch_size))
        assert len(a) == len(b)
        for got, want in zip(a, b, strict=True):
            assert isinstance(got.observations, GraphBatch)
            expected = padded_to_batch(want.observations)
            for t1, t2 in zip(got.observations[:5], expected[:5]):
                torch.testing.assert_close(t1, t2)
            torch.testing.assert_close(got.actions, want.actions)
            for name in ("old_values", "old_log_prob", "advantages", "returns"):
                torch.testing.assert_close(getattr(got, name), getattr(want, name))


def test_stores_only_real_rows_and_resets():
    ours = GraphRolloutBuffer(32, SPACE, ACTIONS, device="cpu", n_envs=2)
    reference = DictRolloutBuffer(32, SPACE, ACTIONS, device="cpu", n_envs=2)
    fill([ours, reference], 32, 2)
    padded = sum(v.nbytes for v in reference.observations.values()) + reference.actions.nbytes
    assert ours.nbytes < padded / 2
    with pytest.raises(ValueError, match="full"):
        fill([ours], 1, 2)
    before = ours.nbytes
    ours.reset()
    assert ours.pos == 0 and not ours.full and ours.nbytes < before / 2  # the graphs are dropped
    fill([ours], 32, 2, seed=1)
    assert sum(b.observations.num_graphs for b in ours.get(10)) == 64


def test_rejects_edges_at_padded_slots():
    buffer = GraphRolloutBuffer(4, SPACE, ACTIONS, device="cpu")
    obs = {k: v[None].copy() for k, v in SPACE.encode(np.zeros((2, 2)), np.array([[0], [1]])).items()}
    obs["edge_index"][0, 1, 0] = 4  # slot 4 is padding
    with pytest.raises(ValueError, match="padded vertex slot"):
        buffer.add(obs, np.zeros((1, 7)), np.zeros(1), np.zeros(1), torch.zeros(1, 1), torch.zeros(1))
