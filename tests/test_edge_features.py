"""Edge features: GraphSpace(edge_features=k) through encode/decode, batching, both buffers and the
policies, and the layer reads them."""

import copy
import pickle
import warnings

import numpy as np
import pytest
import torch
from gymnasium import spaces
from learner_fixtures import filled_learner
from stable_baselines3.common.buffers import DictReplayBuffer, DictRolloutBuffer
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import obs_as_tensor
from torch_geometric.data import Batch, Data

from sb3_graph import PPO, SAC, TD3, GraphReplayBuffer, GraphRolloutBuffer, GraphSpace
from sb3_graph.common.batching import derived_indices, padded_to_batch
from sb3_graph.common.layers import use_compiled_kernels
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)

SPACE = GraphSpace(max_nodes=6, node_features=2, max_edges=12, num_relations=2, edge_features=3, seed=0)
ACTIONS = spaces.Box(-1.0, 1.0, (6,), np.float32)


def test_space_round_trip_and_errors():
    x = np.arange(8, dtype=np.float32).reshape(4, 2)
    edge_index = np.array([[0, 1, 3], [1, 2, 0]])
    edge_type = np.array([0, 1, 1])
    edge_attr = np.arange(9, dtype=np.float32).reshape(3, 3)
    obs = SPACE.encode(x, edge_index, edge_type, edge_attr)
    assert obs["edge_attr"].shape == (12, 3) and np.all(obs["edge_attr"][3:] == 0)
    assert SPACE.contains(obs)
    for got, want in zip(SPACE.decode(obs), (x, edge_index, edge_type, edge_attr), strict=True):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="edge_attr of shape"):
        SPACE.encode(x, edge_index, edge_type)
    with pytest.raises(ValueError, match=r"edge_attr must have shape \(3, 3\)"):
        SPACE.encode(x, edge_index, edge_type, edge_attr[:, :2])
    with pytest.raises(ValueError, match="edge_features=0"):
        GraphSpace(6, 2, 12).encode(x, edge_index, None, edge_attr)
    assert SPACE != GraphSpace(6, 2, 12, 2) and SPACE == pickle.loads(pickle.dumps(SPACE))
    assert "edge_features=3" in repr(SPACE) and "edge_attr" not in GraphSpace(6, 2, 12).spaces
    assert SPACE.contains(SPACE.sample())


def test_padded_to_batch_carries_edge_features_like_pyg():
    graphs = [SPACE.sample() for _ in range(10)]
    batch = padded_to_batch(obs_as_tensor({k: np.stack([g[k] for g in graphs]) for k in graphs[0]}, "cpu"))
    reference = Batch.from_data_list(
        [
            Data(x=torch.as_tensor(x), edge_index=torch.as_tensor(ei), edge_attr=torch.as_tensor(ea))
            for x, ei, _, ea in (SPACE.decode(g) for g in graphs)
        ]
    )
    torch.testing.assert_close(batch.edge_index, reference.edge_index)
    torch.testing.assert_close(batch.edge_attr, reference.edge_attr)
    joint = torch.cat([batch, batch])
    torch.testing.assert_close(joint.edge_attr, torch.cat([batch.edge_attr, batch.edge_attr]))


def stacked(graphs):
    return {k: np.stack([g[k] for g in graphs]) for k in graphs[0]}


def test_replay_buffer_round_trip_matches_dict_buffer():
    ours = GraphReplayBuffer(20, SPACE, ACTIONS, device="cpu", n_envs=2, initial_capacity=4)
    reference = DictReplayBuffer(20, SPACE, ACTIONS, device="cpu", n_envs=2)
    rng = np.random.default_rng(0)
    current = [SPACE.sample() for _ in range(2)]
    for _ in range(30):  # the ring wraps; episodes link next observations to the following ones
        following = [SPACE.sample() for _ in range(2)]
        done = rng.random(2) < 0.3
        action = rng.uniform(-1, 1, (2, 6)).astype(np.float32)
        for buffer in (ours, reference):
            buffer.add(stacked(current), stacked(following), action, rng.standard_normal(2), done, [{}, {}])
        current = [SPACE.sample() if d else f for f, d in zip(following, done)]
    for seed in range(3):
        np.random.seed(seed)  # noqa: NPY002 (SB3 samples with the global generator)
        a = ours.sample(32)
        np.random.seed(seed)  # noqa: NPY002
        b = reference.sample(32)
        for got, want in ((a.observations, b.observations), (a.next_observations, b.next_observations)):
            want = padded_to_batch(want)
            torch.testing.assert_close(got.edge_attr, want.edge_attr)
            torch.testing.assert_close(got.edge_index, want.edge_index)
    clone = pickle.loads(pickle.dumps(ours))
    np.random.seed(0)  # noqa: NPY002
    c = clone.sample(8)
    np.random.seed(0)  # noqa: NPY002
    torch.testing.assert_close(c.observations.edge_attr, ours.sample(8).observations.edge_attr)


def test_rollout_buffer_round_trip():
    buffer = GraphRolloutBuffer(5, SPACE, ACTIONS, device="cpu", n_envs=2)
    reference = DictRolloutBuffer(5, SPACE, ACTIONS, device="cpu", n_envs=2)
    rng = np.random.default_rng(1)
    for step in range(5):
        obs = stacked([SPACE.sample() for _ in range(2)])
        action = rng.standard_normal((2, 6)).astype(np.float32)
        args = (action, rng.standard_normal(2), np.array([step == 0] * 2), torch.randn(2, 1), torch.randn(2))
        buffer.add(obs, *args)
        reference.add(obs, *args)
    np.random.seed(0)  # noqa: NPY002
    ours = list(buffer.get(4))
    np.random.seed(0)  # noqa: NPY002
    theirs = list(reference.get(4))
    for a, b in zip(ours, theirs, strict=True):
        torch.testing.assert_close(a.observations.edge_attr, padded_to_batch(b.observations).edge_attr)


class EdgeFeatureEnv(MaxNeighbourEnv):
    """The toy task with edge features: the target is the largest ``x_j[0] * e_ji[0]`` over relation-0
    in-neighbours, so a policy must read the edge features to solve it."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        base = self.observation_space
        self.observation_space = GraphSpace(
            base.max_nodes,
            base.node_features,
            base.max_edges,
            base.num_relations,
            low=-1.0,
            high=1.0,
            edge_features=2,
            edge_low=-1.0,
            edge_high=1.0,
        )

    def _new_graph(self):
        space, rng = self.observation_space, self.np_random
        n = int(rng.integers(2, space.max_nodes + 1))
        x = rng.uniform(-1, 1, (n, space.node_features)).astype(np.float32)
        e = min(int(rng.poisson(self.edges_per_node * n)) + 1, space.max_edges)
        src = rng.integers(0, n, e)
        dst = (src + rng.integers(1, n, e)) % n
        edge_type = rng.integers(0, space.num_relations, e)
        edge_attr = rng.uniform(-1, 1, (e, 2)).astype(np.float32)
        signal = edge_type == 0
        target = np.full(n, -np.inf, np.float32)
        np.maximum.at(target, dst[signal], x[src[signal], 0] * edge_attr[signal, 0])
        self._target = np.where(np.isfinite(target), target, 0.0).astype(np.float32)
        return space.encode(x, np.stack([src, dst]), edge_type, edge_attr)


def test_edge_feature_env_passes_the_checker():
    check_env(EdgeFeatureEnv(), warn=False)


@pytest.mark.parametrize("algo", [TD3, SAC, PPO])
def test_policies_read_edge_features(algo):
    kwargs = dict(n_steps=16, batch_size=8) if algo is PPO else dict(learning_starts=10, batch_size=8)
    model = algo("GraphPolicy", EdgeFeatureEnv(), seed=0, policy_kwargs=dict(encoder_dim=16, conv_dims=[16]), **kwargs)
    model.learn(32)
    obs, _ = EdgeFeatureEnv().reset(seed=5)  # at least one edge
    changed = {k: v.copy() for k, v in obs.items()}
    changed["edge_attr"] += 0.5
    a = model.predict(obs, deterministic=True)[0]
    b = model.predict(changed, deterministic=True)[0]
    assert not np.allclose(a, b)  # the edge features reach the actions
    changed["edge_attr"][int(obs["edge_mask"].sum()) :] = 9.0  # padded edge slots do not
    np.testing.assert_allclose(model.predict(changed, deterministic=True)[0], b)
    # Switching them off: the same space, a policy that ignores them.
    blind = algo("GraphPolicy", EdgeFeatureEnv(), seed=0, policy_kwargs=dict(use_edge_features=False), **kwargs)
    np.testing.assert_allclose(blind.predict(obs, deterministic=True)[0], blind.predict(changed, deterministic=True)[0])


@pytest.mark.parametrize("name", ["TD3", "DDPG", "SAC", "TQC", "PPO"])
def test_learners_with_edge_features_update_as_the_pytorch_formulation(name):
    """Issue #27: the convolutions with edge features run in the compiled kernels; copies of one
    learner, trained on the same transitions with the kernels on and off (the formulation before),
    end with the same weights to float tolerance, the edge weights included."""
    if name == "PPO":  # one rollout and its update, to fill the buffer; then train again on it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = PPO(
                "GraphPolicy", EdgeFeatureEnv(min_nodes=0), n_steps=32, batch_size=16, n_epochs=2, seed=0,
                policy_kwargs=dict(encoder_dim=16, conv_dims=[16, 16]),
            )  # fmt: skip
        model.set_logger(configure(None, []))
        model.learn(32)
    else:
        model = filled_learner(name, EdgeFeatureEnv(min_nodes=0))
    states = []
    for compiled in (True, False):
        learner = copy.deepcopy(model)
        previous = use_compiled_kernels(compiled)
        try:
            torch.manual_seed(1)
            np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
            derived_indices.clear()
            learner.train() if name == "PPO" else learner.train(gradient_steps=4, batch_size=16)
        finally:
            use_compiled_kernels(previous)
        states.append(learner.policy.state_dict())
    assert set(states[0]) == set(states[1])
    for key, value in states[0].items():
        torch.testing.assert_close(value, states[1][key], msg=key)
    edge_weights = [k for k in states[0] if k.endswith("edge_weight")]
    assert edge_weights and any(not torch.equal(states[0][k], model.policy.state_dict()[k]) for k in edge_weights)
