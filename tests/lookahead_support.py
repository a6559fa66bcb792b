"""What the tests of ``lookahead`` share: a run's commands and a busy scene."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs
from envs.planners import make_planner
from envs.simulation.traffic import generate_scenario


def drive(planner, seconds: float = 30.0, seed: int = 11) -> list[np.ndarray]:
    """The commands of ``planner`` over a run of ``seconds`` on a generated 4-way scenario."""
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    env.reset(seed=seed, options={"scenario": generate_scenario("4way", seconds, seed, rate_range=(0.4, 0.4))})
    planner.reset(seed)
    commands, done = [], False
    while not done:
        acc = planner.act(env.unwrapped.scene())
        commands.append(acc)
        _, _, terminated, truncated, _ = env.step(env.unwrapped.accelerations_to_action(acc))
        done = terminated or truncated
    return commands


def busy_scene():
    """The scene after 12 s of full throttle + shield at 0.5 veh/s per major lane."""
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    env.reset(seed=5, options={"scenario": generate_scenario("4way", 40.0, 5, rate_range=(0.5, 0.5))})
    planner = make_planner("fullthrottle+shield")
    for _ in range(60):
        env.step(env.unwrapped.accelerations_to_action(planner.act(env.unwrapped.scene())))
    return env.unwrapped.scene()
