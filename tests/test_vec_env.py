"""The graph space passes SB3's checker and vectorized environments unchanged."""

import numpy as np
import pytest
import torch
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_graph import TD3, GraphReplayBuffer
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)


def test_check_env():
    check_env(MaxNeighbourEnv(), warn=False)
    check_env(MaxNeighbourEnv(min_nodes=0, num_relations=1, node_features=1), warn=False)


def test_toy_env_is_registered():
    import gymnasium as gym

    from sb3_graph.toy_envs import MAX_NEIGHBOUR_ID

    env = gym.make(MAX_NEIGHBOUR_ID, max_nodes=4)
    assert env.action_space.shape == (4,) and env.observation_space.max_nodes == 4


def test_toy_env_rewards_perfect_actions():
    env = MaxNeighbourEnv()
    env.reset(seed=0)
    for _ in range(5):
        _, reward, *_ = env.step(np.pad(env._target, (0, 8 - len(env._target))))
        assert reward == 0.0
    with pytest.raises(ValueError, match="min_nodes"):
        MaxNeighbourEnv(max_nodes=3, min_nodes=4)


def test_toy_env_renders_features_and_targets():
    env = MaxNeighbourEnv(max_nodes=4, min_nodes=2, render_mode="rgb_array")
    env.reset(seed=1)
    n = len(env._target)
    image = env.render()
    assert image.shape == (32, 64, 3) and image.dtype == np.uint8
    expected = np.round((env._target + 1) * 127.5)
    np.testing.assert_allclose(image[::8, 40, 0][:n], expected, atol=1)
    assert (image[8 * n :, :, 1] == 0).all() and (image[8 * n :, :, 0] == 255).all()
    assert MaxNeighbourEnv().render() is None
    with pytest.raises(ValueError, match="render_mode must be one of"):
        MaxNeighbourEnv(render_mode="human")


@pytest.mark.parametrize("vec_env_class", [DummyVecEnv, SubprocVecEnv])
def test_two_envs(vec_env_class):
    env = vec_env_class([lambda: MaxNeighbourEnv(episode_length=5)] * 2)
    try:
        model = TD3("GraphPolicy", env, learning_starts=20, batch_size=16, buffer_size=60, seed=0)
        assert isinstance(model.replay_buffer, GraphReplayBuffer) and model.replay_buffer.n_envs == 2
        model.learn(100)
        assert model.replay_buffer.full
        obs = env.reset()
        actions, _ = model.predict(obs, deterministic=True)
        assert actions.shape == (2, 8)
        assert np.all(actions[obs["node_mask"] == 0] == 0)
    finally:
        env.close()
