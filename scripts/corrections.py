"""How a residual policy corrects its base planner behind the shield: is it planning, or saturated?

Runs each residual planner file behind the shield through main-job scenarios (the harness's own
environment and loop) and counts, over the vehicle-steps, the policy's correction (its action in
[-1, 1], before ``residual_scale``): at the top bound (over full throttle a correction >= 0 changes
nothing: the bounds clip it), negative (it brakes against its base), and its mean::

    python scripts/corrections.py experiments/shielded_training/features_s*/final_model.safetensors --scenarios 2

A policy whose corrections are all at +1 is its base planner, whatever its file says.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.planners import make_planner
from envs.planners.residual import ResidualPlanner
from envs.simulation.traffic import generate_scenario


class _Spy:
    """Wraps the learned planner of a residual planner and keeps its actions."""

    def __init__(self, planner) -> None:
        self.planner = planner
        self.actions: list[np.ndarray] = []

    def __getattr__(self, name):
        return getattr(self.planner, name)

    def act(self, scene) -> np.ndarray:
        command = np.asarray(self.planner.act(scene), float)
        self.actions.append(command / scene.a_max)
        return command


def corrections(path: str, scenarios: int, seed: int, duration: float) -> dict[str, float]:
    """Share of vehicle-steps at the top bound (>= 0.999), negative (< 0), and the mean correction.

    :param path: a residual policy file
    :param scenarios: main-job scenarios to run
    :param seed: seed of the scenarios (``sb3-graph evaluate --seed``)
    :param duration: seconds per scenario
    """
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    shield = make_planner(path + "+shield")
    residual = shield.planner
    if not isinstance(residual, ResidualPlanner):
        raise SystemExit(f"{path}: not a residual policy (its file names no residual_base)")
    spy = residual.correction = _Spy(residual.correction)
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    rng = np.random.default_rng(seed)
    for i in range(scenarios):
        scenario = generate_scenario(env.unwrapped.layout, duration, rng)
        run_episode(env, shield, scenario, duration, seed=seed + i)
    actions = np.concatenate(spy.actions) if spy.actions else np.zeros(0)
    return {
        "vehicle_steps": actions.size,
        "at_top": float((actions >= 0.999).mean()),
        "negative": float((actions < 0).mean()),
        "mean": float(actions.mean()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", help="residual policy files (.safetensors)")
    parser.add_argument("--scenarios", type=int, default=2, help="main-job scenarios per file (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenarios (default 0)")
    parser.add_argument("--duration", type=float, default=100.0, help="seconds per scenario (default 100)")
    args = parser.parse_args(argv)
    print("file | vehicle-steps | correction at +1 | correction < 0 | mean correction")
    for path in args.files:
        row = corrections(path, args.scenarios, args.seed, args.duration)
        print(f"{path} | {row['vehicle_steps']} | {row['at_top']:.1%} | {row['negative']:.1%} | {row['mean']:+.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
