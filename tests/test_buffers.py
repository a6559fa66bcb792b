"""GraphReplayBuffer: what goes in comes out, FIFO like SB3's buffers, compact, picklable."""

import pickle

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_graph import GraphReplayBuffer, GraphSpace
from sb3_graph.common.batching import GraphBatch, padded_to_batch

torch.set_num_threads(1)

MAX_NODES = 7
SPACE = GraphSpace(max_nodes=MAX_NODES, node_features=2, max_edges=20, num_relations=3, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (MAX_NODES,), np.float32)


def random_graph(rng: np.random.Generator) -> dict[str, np.ndarray]:
    # Sizes vary from empty graphs to full ones so the pools wrap and grow.
    n = int(rng.integers(0, MAX_NODES + 1))
    e = int(rng.integers(0, 21)) if n > 1 else 0
    src = rng.integers(0, max(n, 1), e)
    dst = rng.integers(0, max(n, 1), e)
    return SPACE.encode(rng.standard_normal((n, 2)), np.stack([src, dst]), rng.integers(0, 3, e))


def fill(buffers, steps: int, n_envs: int, seed: int = 0) -> list[dict]:
    """Add ``steps`` rows of transitions to every buffer; reward = unique transition id."""
    rng = np.random.default_rng(seed)
    record = []
    for step in range(steps):
        obs = [random_graph(rng) for _ in range(n_envs)]
        next_obs = [random_graph(rng) for _ in range(n_envs)]
        action = rng.uniform(-1, 1, (n_envs, MAX_NODES)).astype(np.float32)
        reward = np.arange(step * n_envs, (step + 1) * n_envs, dtype=np.float32)
        done = rng.random(n_envs) < 0.3
        truncated = rng.random(n_envs) < 0.5
        infos = [{"TimeLimit.truncated": bool(t)} for t in truncated]
        stacked = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
        stacked_next = {k: np.stack([o[k] for o in next_obs]) for k in next_obs[0]}
        for buffer in buffers:
            buffer.add(stacked, stacked_next, action, reward, done, infos)
        for i in range(n_envs):
            record.append(
                dict(
                    obs=obs[i],
                    next_obs=next_obs[i],
                    action=action[i],
                    done=float(done[i] and not truncated[i]),
                )
            )
    return record


def split(graphs: GraphBatch, i: int):
    nodes = graphs.batch == i
    first = int(torch.nonzero(nodes)[0]) if nodes.any() else 0
    edges = nodes[graphs.edge_index[0]] if graphs.num_edges else torch.zeros(0, dtype=torch.bool)
    return (
        graphs.x[nodes],
        graphs.edge_index[:, edges] - first,
        graphs.edge_type[edges],
        graphs.node_slot[nodes],
    )


def assert_same_graph(graphs: GraphBatch, i: int, expected: dict[str, np.ndarray]):
    x, edge_index, edge_type, slots = split(graphs, i)
    ex, eei, eet = SPACE.decode(expected)
    np.testing.assert_array_equal(x.numpy(), ex)
    np.testing.assert_array_equal(edge_index.numpy(), eei)
    np.testing.assert_array_equal(edge_type.numpy(), eet)
    np.testing.assert_array_equal(slots.numpy(), np.arange(len(ex)))


@pytest.mark.parametrize("n_envs", [1, 2])
def test_round_trip_after_wrap_around(n_envs):
    buffer = GraphReplayBuffer(10 * n_envs, SPACE, ACTIONS, device="cpu", n_envs=n_envs, initial_capacity=4)
    record = fill([buffer], steps=37, n_envs=n_envs)
    assert buffer.full and buffer.pos == 37 % 10
    np.random.seed(0)  # noqa: NPY002 (SB3 samples with the global generator)
    samples = buffer.sample(200)
    assert isinstance(samples, ReplayBufferSamples) and samples.discounts is None
    ids = samples.rewards.squeeze(1).long().numpy()
    # Only the last 10 rows of transitions are live: FIFO as in SB3.
    assert set(ids.tolist()) == set(range((37 - 10) * n_envs, 37 * n_envs))
    assert samples.actions.shape == (200, MAX_NODES)
    for i, transition_id in enumerate(ids):
        expected = record[transition_id]
        assert_same_graph(samples.observations, i, expected["obs"])
        assert_same_graph(samples.next_observations, i, expected["next_obs"])
        n = SPACE.num_nodes(expected["obs"])
        np.testing.assert_array_equal(samples.actions[i, :n].numpy(), expected["action"][:n])
        assert torch.all(samples.actions[i, n:] == 0)
        assert samples.dones[i, 0].item() == expected["done"]


def test_same_batches_as_dict_replay_buffer():
    ours = GraphReplayBuffer(24, SPACE, ACTIONS, device="cpu", n_envs=2, initial_capacity=8)
    reference = DictReplayBuffer(24, SPACE, ACTIONS, device="cpu", n_envs=2)
    fill([ours, reference], steps=200, n_envs=2, seed=3)  # the pools wrap and grow many times
    for seed in range(3):
        np.random.seed(seed)  # noqa: NPY002 (SB3 samples with the global generator)
        a = ours.sample(64)
        np.random.seed(seed)  # noqa: NPY002 (SB3 samples with the global generator)
        b = reference.sample(64)
        expected = padded_to_batch(b.observations)
        expected_next = padded_to_batch(b.next_observations)
        for got, want in ((a.observations, expected), (a.next_observations, expected_next)):
            for t1, t2 in zip(got[:5], want[:5]):
                torch.testing.assert_close(t1, t2)
        mask = b.observations["node_mask"].bool()
        torch.testing.assert_close(a.actions[mask], b.actions[mask])
        torch.testing.assert_close(a.rewards, b.rewards)
        torch.testing.assert_close(a.dones, b.dones)


def test_timeouts_ignored_when_not_handled():
    buffer = GraphReplayBuffer(50, SPACE, ACTIONS, device="cpu", handle_timeout_termination=False)
    rng = np.random.default_rng(0)
    g = {k: v[None] for k, v in random_graph(rng).items()}
    buffer.add(g, g, np.zeros((1, MAX_NODES)), np.zeros(1), np.ones(1), [{"TimeLimit.truncated": True}])
    assert buffer.sample(4).dones.min().item() == 1.0


def test_pickle_round_trip_and_memory():
    buffer = GraphReplayBuffer(16, SPACE, ACTIONS, device="cpu", n_envs=2, initial_capacity=2)
    reference = DictReplayBuffer(16, SPACE, ACTIONS, device="cpu", n_envs=2)
    fill([buffer], steps=13, n_envs=2, seed=5)
    clone = pickle.loads(pickle.dumps(buffer))
    np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
    a = buffer.sample(32)
    np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
    b = clone.sample(32)
    for t1, t2 in zip(a.observations[:5], b.observations[:5]):
        torch.testing.assert_close(t1, t2)
    torch.testing.assert_close(a.actions, b.actions)
    torch.testing.assert_close(a.rewards, b.rewards)
    padded = sum(v.nbytes for v in reference.observations.values()) * 2 + reference.actions.nbytes
    assert buffer.nbytes < padded
    buffer.reset()
    assert buffer.size() == 0 and buffer.obs_nodes.used == 0


def test_errors():
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        GraphReplayBuffer(10, SPACE, ACTIONS, optimize_memory_usage=True)
    with pytest.raises(ValueError, match="action_space"):
        GraphReplayBuffer(10, SPACE, spaces.Box(-1, 1, (3,), np.float32))
    buffer = GraphReplayBuffer(10, SPACE, ACTIONS, device="cpu")
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(2)
    g = {k: v[None].copy() for k, v in SPACE.encode(np.zeros((2, 2))).items()}
    g["node_mask"][0] = [0, 1, 1, 0, 0, 0, 0]
    with pytest.raises(ValueError, match="node_mask"):
        buffer.add(g, g, np.zeros((1, MAX_NODES)), np.zeros(1), np.zeros(1), [{}])


def test_pools_reuse_space_after_wrap_around():
    # Graphs of one size: once the ring is full, the pools are trimmed to the live rows (+ slack)
    # and overwritten rows are reused in place, so the capacity never changes again.
    buffer = GraphReplayBuffer(40, SPACE, ACTIONS, device="cpu", n_envs=2, initial_capacity=4)
    g = {k: np.stack([v, v]) for k, v in SPACE.encode(np.ones((5, 2)), np.array([[0, 1], [1, 2]])).items()}
    actions = np.ones((2, MAX_NODES), np.float32)
    for _ in range(20):
        buffer.add(g, g, actions, np.zeros(2), np.zeros(2), [{}, {}])
    capacities = [pool.capacity for pool in buffer.pools]
    for pool in buffer.pools:
        assert pool.used <= pool.capacity <= 1.1 * pool.used + 2 * 2 * 5 + 16
    for _ in range(100):
        buffer.add(g, g, actions, np.zeros(2), np.zeros(2), [{}, {}])
    assert [pool.capacity for pool in buffer.pools] == capacities
    samples = buffer.sample(8)
    assert samples.observations.num_nodes == 40 and samples.observations.num_edges == 16


class EpisodeStream:
    """Transitions as SB3 adds them: the next observation is the following observation except at
    episode ends, where it is the terminal observation and the following one is a reset."""

    def __init__(self, n_envs: int, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.n_envs = n_envs
        self.current = [random_graph(self.rng) for _ in range(n_envs)]

    def add_to(self, buffers, steps: int) -> None:
        for _ in range(steps):
            next_obs = []
            for i in range(self.n_envs):
                # Sometimes the graph does not change at all, e.g. an empty scene.
                stay = self.rng.random() < 0.1
                next_obs.append(
                    {k: v.copy() for k, v in self.current[i].items()} if stay else random_graph(self.rng)
                )
            done = self.rng.random(self.n_envs) < 0.2
            stacked = {k: np.stack([o[k] for o in self.current]) for k in next_obs[0]}
            stacked_next = {k: np.stack([o[k] for o in next_obs]) for k in next_obs[0]}
            action = self.rng.uniform(-1, 1, (self.n_envs, MAX_NODES)).astype(np.float32)
            reward = self.rng.standard_normal(self.n_envs).astype(np.float32)
            for buffer in buffers:
                buffer.add(stacked, stacked_next, action, reward, done, [{} for _ in range(self.n_envs)])
            self.current = [random_graph(self.rng) if d else o for o, d in zip(next_obs, done)]


def assert_same_samples(ours, reference, seeds=range(3), batch_size=128):
    for seed in seeds:
        np.random.seed(seed)  # noqa: NPY002 (SB3 samples with the global generator)
        a = ours.sample(batch_size)
        np.random.seed(seed)  # noqa: NPY002
        b = reference.sample(batch_size)
        expected, expected_next = padded_to_batch(b.observations), padded_to_batch(b.next_observations)
        for got, want in ((a.observations, expected), (a.next_observations, expected_next)):
            for t1, t2 in zip(got[:5], want[:5]):
                torch.testing.assert_close(t1, t2)
        torch.testing.assert_close(
            a.actions, b.actions if isinstance(b.observations, GraphBatch) else a.actions
        )
        mask = b.observations["node_mask"].bool()
        torch.testing.assert_close(a.actions[mask], b.actions[mask])
        assert torch.all(a.actions[~mask] == 0)
        torch.testing.assert_close(a.rewards, b.rewards)
        torch.testing.assert_close(a.dones, b.dones)


@pytest.mark.parametrize(("buffer_size", "n_envs"), [(30, 1), (24, 2), (9, 3)])
def test_episodes_store_next_observations_once(buffer_size, n_envs):
    ours = GraphReplayBuffer(buffer_size, SPACE, ACTIONS, device="cpu", n_envs=n_envs, initial_capacity=4)
    reference = DictReplayBuffer(buffer_size, SPACE, ACTIONS, device="cpu", n_envs=n_envs)
    stream = EpisodeStream(n_envs, seed=buffer_size)
    stream.add_to([ours, reference], 7)  # before the ring wraps
    assert_same_samples(ours, reference)
    stream.add_to([ours, reference], 150)  # many wraps
    assert_same_samples(ours, reference)
    # Within an episode the next observation is the following one: stored once. Only the newest
    # transitions (no successor yet) and episode ends keep their own copy.
    linked = ~ours.dones.astype(bool)
    linked[(ours.pos - 1) % ours.buffer_size] = False
    assert linked.any() and np.all(ours.next_is_successor[linked])
    own_rows = ours.next_obs_nodes.count[~ours.next_is_successor].sum()
    assert ours.next_obs_nodes.used == own_rows < ours.obs_nodes.used
    # A pickled copy goes on exactly like the original.
    clone = pickle.loads(pickle.dumps(ours))
    stream.add_to([ours, clone, reference], 23)
    assert_same_samples(ours, reference)
    assert_same_samples(clone, reference)


def test_edges_at_padded_slots_or_unknown_relations_are_rejected():
    buffer = GraphReplayBuffer(10, SPACE, ACTIONS, device="cpu", n_envs=2)
    good = SPACE.encode(np.zeros((3, 2)), np.array([[0, 1], [1, 2]]), np.array([0, 2]))
    g = {k: np.stack([v, v]) for k, v in good.items()}
    args = (np.zeros((2, MAX_NODES)), np.zeros(2), np.zeros(2), [{}, {}])
    buffer.add(g, g, *args)
    bad = {k: v.copy() for k, v in g.items()}
    bad["edge_index"][1, 1, 1] = 5  # env 1: its second edge points at padded slot 5
    with pytest.raises(ValueError, match=r"padded vertex slot .*\(3 real vertices\)"):
        buffer.add(g, bad, *args)
    bad = {k: v.copy() for k, v in g.items()}
    bad["edge_type"][0, 0] = 3  # relation 3 of 3
    with pytest.raises(ValueError, match=r"num_relations=3"):
        buffer.add(bad, g, *args)
    # Padded edge slots are never read: anything may sit there.
    padded = {k: v.copy() for k, v in g.items()}
    padded["edge_index"][:, :, 2:] = 6
    padded["edge_type"][:, 2:] = 9
    buffer.add(padded, padded, *args)


@pytest.mark.parametrize(("n_envs", "steps"), [(1, 9), (2, 30)])
def test_n_step_returns_equal_sb3_n_step_buffer(n_envs, steps):
    # SB3's NStepReplayBuffer takes no Dict observations: it stores each transition's id as a Box
    # observation; ours stores graphs whose first feature is that id.
    from stable_baselines3.common.buffers import NStepReplayBuffer

    ids = spaces.Box(-1e6, 1e6, (1,), np.float32)
    reference = NStepReplayBuffer(12 * n_envs, ids, ACTIONS, device="cpu", n_envs=n_envs, n_steps=3, gamma=0.9)
    ours = GraphReplayBuffer(12 * n_envs, SPACE, ACTIONS, device="cpu", n_envs=n_envs, n_steps=3, gamma=0.9)
    rng = np.random.default_rng(n_envs)
    for step in range(steps):  # ring of 12 rows: wraps for 30 steps
        ident = np.arange(n_envs) + 100 * step
        graph = [SPACE.encode(np.full((2, 2), i, np.float32)) for i in ident]
        following = [SPACE.encode(np.full((2, 2), i + 0.5, np.float32)) for i in ident]  # "next" of id i
        done = rng.random(n_envs) < 0.2
        infos = [{"TimeLimit.truncated": bool(t)} for t in rng.random(n_envs) < 0.2]
        reward = rng.standard_normal(n_envs)
        action = np.zeros((n_envs, MAX_NODES))
        ours.add(*[{k: np.stack([g[k] for g in gs]) for k in gs[0]} for gs in (graph, following)], action, reward,
                 done, infos)  # fmt: skip
        reference.add(ident[:, None], ident[:, None] + 0.5, action, reward, done, infos)
    for seed in range(3):
        np.random.seed(seed)  # noqa: NPY002 (SB3 samples with the global generator)
        a = ours.sample(64)
        np.random.seed(seed)  # noqa: NPY002
        b = reference.sample(64)
        for name in ("rewards", "dones", "discounts"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name))
        assert torch.all(b.discounts < 0.9 + 1e-6) and torch.any(b.discounts < 0.9**2)  # windows of 1 to 3
        first = a.next_observations.x[a.next_observations.node_slot == 0, 0]
        torch.testing.assert_close(first, b.next_observations[:, 0])
        torch.testing.assert_close(a.observations.x[a.observations.node_slot == 0, 0], b.observations[:, 0])
