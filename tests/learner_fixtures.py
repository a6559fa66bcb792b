"""Learners whose replay buffer holds random-action transitions of a toy graph task (the tests of
the learners' updates share them)."""

import warnings

from stable_baselines3.common.logger import configure

import sb3_graph
from sb3_graph.toy_envs import MaxNeighbourEnv

SMALL = dict(encoder_dim=16, conv_dims=[16, 16])


def filled_learner(name: str, env=None, transitions: int = 64):
    """``sb3_graph.<name>`` with small graph networks (TQC: 5 quantiles), a silent logger, and
    ``transitions`` random actions of ``env`` (default ``MaxNeighbourEnv(min_nodes=0)``) in its
    replay buffer (batch 16, learning from the start).

    :param name: an off-policy algorithm of ``sb3_graph``
    :param env: the environment (its spaces and transitions)
    :param transitions: transitions to add
    """
    env = MaxNeighbourEnv(min_nodes=0) if env is None else env
    policy_kwargs = dict(SMALL, n_quantiles=5) if name == "TQC" else dict(SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = getattr(sb3_graph, name)(
            "GraphPolicy", env, seed=0, learning_starts=0, batch_size=16, buffer_size=200, policy_kwargs=policy_kwargs
        )
    model.set_logger(configure(None, []))
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(transitions):
        action = env.action_space.sample() * obs["node_mask"]
        next_obs, reward, terminated, truncated, _ = env.step(action)
        stack = lambda o: {k: v[None] for k, v in o.items()}  # noqa: E731
        model.replay_buffer.add(stack(obs), stack(next_obs), action[None], [reward], [terminated], [{}])
        obs = env.reset()[0] if terminated or truncated else next_obs
    return model
