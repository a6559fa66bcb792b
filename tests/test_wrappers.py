"""GraphObservation: gymnasium Graph observations become GraphSpace observations that SB3 runs."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.spaces import GraphInstance
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env

from sb3_graph import PPO, GraphSpace
from sb3_graph.wrappers import GraphObservation

torch.set_num_threads(1)


class FixedGraphEnv(gym.Env):
    """Returns the GraphInstances it is given, in turn; action: one value per vertex slot."""

    def __init__(self, observation_space, instances, max_nodes=4):
        self.observation_space = observation_space
        self.action_space = spaces.Box(-1.0, 1.0, (max_nodes,), np.float32)
        self.instances = instances
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.instances[0], {}

    def step(self, action):
        self.t += 1
        return self.instances[self.t % len(self.instances)], 0.0, False, self.t >= 3, {}


NODES = np.array([[0.5, -1.0], [0.25, 0.0], [1.0, 2.0]], np.float32)
LINKS = np.array([[0, 1], [2, 1], [1, 0]])


def test_box_nodes_and_discrete_edges_become_vertices_and_relations():
    graph_space = spaces.Graph(node_space=spaces.Box(-3, 3, (2,)), edge_space=spaces.Discrete(3, start=1))
    instance = GraphInstance(nodes=NODES, edges=np.array([1, 3, 2]), edge_links=LINKS)
    env = GraphObservation(FixedGraphEnv(graph_space, [instance]), max_nodes=4, max_edges=5)
    space = env.observation_space
    assert isinstance(space, GraphSpace) and (space.max_nodes, space.node_features, space.num_relations) == (4, 2, 3)
    assert space.edge_features == 0 and (space.low, space.high) == (-3.0, 3.0)
    obs, _ = env.reset(seed=0)
    expected = space.encode(NODES, LINKS.T, np.array([0, 2, 1]))  # (source, target) rows; ids - start
    for key in expected:
        np.testing.assert_array_equal(obs[key], expected[key])
    check_env(env, warn=False)


def test_box_edges_become_edge_features_and_discrete_ones_can_too():
    graph_space = spaces.Graph(node_space=spaces.Box(-3, 3, (2,)), edge_space=spaces.Box(0, 1, (2,)))
    attr = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]], np.float32)
    env = GraphObservation(FixedGraphEnv(graph_space, [GraphInstance(NODES, attr, LINKS)]), 4, 5)
    obs, _ = env.reset()
    x, edge_index, edge_type, edge_attr = env.observation_space.decode(obs)
    np.testing.assert_array_equal(edge_attr, attr)
    np.testing.assert_array_equal(edge_index, LINKS.T)
    assert np.all(edge_type == 0) and env.observation_space.num_relations == 1
    one_hot_space = spaces.Graph(node_space=spaces.Box(-3, 3, (2,)), edge_space=spaces.Discrete(2))
    instance = GraphInstance(NODES, np.array([1, 0, 1]), LINKS)
    env = GraphObservation(FixedGraphEnv(one_hot_space, [instance]), 4, 5, discrete_edges="features")
    edge_attr = env.observation_space.decode(env.reset()[0])[3]
    np.testing.assert_array_equal(edge_attr, [[0, 1], [1, 0], [0, 1]])


def test_discrete_nodes_no_edge_space_and_empty_graphs():
    graph_space = spaces.Graph(node_space=spaces.Discrete(3), edge_space=None)
    instances = [
        GraphInstance(np.array([2, 0]), None, np.array([[0, 1]])),
        GraphInstance(np.zeros(0, np.int64), None, np.zeros((0, 2), np.int64)),
    ]
    env = GraphObservation(FixedGraphEnv(graph_space, instances), 4, 2)
    obs, _ = env.reset()
    x, edge_index, edge_type = env.observation_space.decode(obs)
    np.testing.assert_array_equal(x, [[0, 0, 1], [1, 0, 0]])
    np.testing.assert_array_equal(edge_index, [[0], [1]])
    obs = env.step(np.zeros(4))[0]
    assert obs["node_mask"].sum() == 0 and obs["edge_mask"].sum() == 0


def test_too_many_vertices_or_edges_and_wrong_spaces_name_the_limit():
    graph_space = spaces.Graph(node_space=spaces.Box(-3, 3, (2,)), edge_space=None)
    env = GraphObservation(FixedGraphEnv(graph_space, [GraphInstance(NODES, None, LINKS)]), max_nodes=2, max_edges=5)
    with pytest.raises(ValueError, match="3 vertices, more than max_nodes=2"):
        env.reset()
    env = GraphObservation(FixedGraphEnv(graph_space, [GraphInstance(NODES, None, LINKS)]), max_nodes=4, max_edges=2)
    with pytest.raises(ValueError, match="3 edges, more than max_edges=2"):
        env.reset()
    with pytest.raises(ValueError, match="gymnasium Graph"):
        GraphObservation(gym.make("CartPole-v1"), 4, 4)
    with pytest.raises(ValueError, match="discrete_edges"):
        GraphObservation(FixedGraphEnv(graph_space, []), 4, 4, discrete_edges="both")


def test_sb3_trains_on_a_wrapped_graph_env():
    from examples.gymnasium_graph_env import NearestLeaderEnv

    env = make_vec_env(
        NearestLeaderEnv,
        n_envs=2,
        wrapper_class=GraphObservation,
        wrapper_kwargs=dict(max_nodes=8, max_edges=16),
        seed=0,
    )
    model = PPO(
        "GraphPolicy", env, n_steps=16, batch_size=16, seed=0, policy_kwargs=dict(encoder_dim=16, conv_dims=[16])
    )
    model.learn(64)
    actions, _ = model.predict(env.reset(), deterministic=True)
    assert actions.shape == (2, 8)
