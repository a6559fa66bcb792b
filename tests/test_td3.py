"""TD3 with GraphPolicy: SB3's training loop unchanged, graph defaults, learning on a toy graph task."""

import numpy as np
import pytest
import stable_baselines3
import torch
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_graph import TD3, GraphPolicy, GraphReplayBuffer
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)


def test_defaults_and_alias():
    model = TD3("GraphPolicy", MaxNeighbourEnv(), learning_starts=10, batch_size=8, seed=0)
    assert isinstance(model.policy, GraphPolicy)
    assert isinstance(model.replay_buffer, GraphReplayBuffer)
    model.learn(40)
    assert model.logger.name_to_value["train/critic_loss"] > 0
    # An explicit buffer class wins over the default.
    model = TD3(GraphPolicy, MaxNeighbourEnv(), replay_buffer_class=DictReplayBuffer, buffer_size=100)
    assert isinstance(model.replay_buffer, DictReplayBuffer)


def test_plain_sb3_td3_works():
    model = stable_baselines3.TD3(GraphPolicy, MaxNeighbourEnv(), learning_starts=10, batch_size=8, seed=0)
    assert isinstance(model.replay_buffer, DictReplayBuffer)
    model.learn(40)
    assert model.logger.name_to_value["train/actor_loss"] != 0


def test_optimize_memory_usage_rejected():
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        TD3("GraphPolicy", MaxNeighbourEnv(), optimize_memory_usage=True)


def mean_return(model, env, episodes):
    if model is None:
        rng = np.random.default_rng(0)
        returns = []
        for episode in range(episodes):
            env.reset(seed=1000 + episode)
            done, total = False, 0.0
            while not done:
                _, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
                total += reward
                done = terminated or truncated
            returns.append(total)
        return float(np.mean(returns))
    env.reset(seed=1000)
    return float(evaluate_policy(model, env, n_eval_episodes=episodes)[0])


@pytest.mark.slow  # test_algorithms.py checks the same in a few hundred steps; this is the longer run
def test_learns_toy_task():
    env = Monitor(MaxNeighbourEnv())
    random_return = mean_return(None, MaxNeighbourEnv(), 30)
    model = TD3("GraphPolicy", env, learning_starts=200, batch_size=64, gamma=0.0, seed=0)
    model.learn(1500)
    learned = mean_return(model, Monitor(MaxNeighbourEnv()), 30)
    # Random scores ~-0.6 per step, a perfect policy 0: demand well over half the gap closed.
    assert learned > 0.4 * random_return, (learned, random_return)


@pytest.mark.slow
def test_learns_toy_task_with_discount_and_two_envs():
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env(MaxNeighbourEnv, n_envs=2, seed=0)
    random_return = mean_return(None, MaxNeighbourEnv(), 30)
    model = TD3("GraphPolicy", env, learning_starts=500, batch_size=128, seed=0)
    model.learn(6000)
    learned = mean_return(model, Monitor(MaxNeighbourEnv()), 30)
    assert learned > 0.3 * random_return, (learned, random_return)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_learns_on_cuda():
    model = TD3("GraphPolicy", MaxNeighbourEnv(), learning_starts=10, batch_size=8, seed=0, device="cuda")
    model.learn(40)
    samples = model.replay_buffer.sample(4)
    assert samples.observations.x.is_cuda and samples.actions.is_cuda
    assert model.predict(MaxNeighbourEnv().observation_space.sample())[0].shape == (8,)
