"""Every algorithm on the toy graph task: error per vertex after the same number of steps, and wall time.

The task is ``sb3_graph.toy_envs.MaxNeighbourEnv`` (``GraphMaxNeighbour-v0``): each vertex must
output the largest first feature among its in-neighbours of relation 0, on a fresh random graph of
1 to 8 vertices every step (a contextual bandit, so ``gamma=0``). The reward is minus the mean
absolute error over the real vertices; this script reports that error, averaged over 30 evaluation
episodes of 8 steps (a uniformly random policy: ~0.6; a perfect one: 0). Every algorithm gets the
same environment steps and networks (encoder 32, two convolutions of 32); the other settings are
the ones of ``tests/test_algorithms.py`` (not tuned per algorithm). One torch thread.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from graph_bench_utils import machine_line, markdown_table
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

import sb3_graph
from sb3_graph.toy_envs import MaxNeighbourEnv

ALGOS = ("TD3", "DDPG", "SAC", "TQC", "CrossQ", "PPO", "A2C")
ENTROPY_ALGOS = ("SAC", "TQC", "CrossQ")


def settings(name: str, ent_coef: str | None = None) -> dict:
    kwargs = dict(gamma=0.0, policy_kwargs=dict(encoder_dim=32, conv_dims=[32, 32]))
    if ent_coef is not None and name in ENTROPY_ALGOS:
        kwargs["ent_coef"] = ent_coef
    if name == "PPO":
        kwargs.update(n_steps=64, batch_size=32, n_epochs=10, learning_rate=3e-3)
    elif name == "A2C":
        kwargs.update(n_steps=16, learning_rate=1e-3)
    else:
        kwargs.update(learning_starts=100, batch_size=32, learning_rate=1e-3)
    return kwargs


def error_per_vertex(model, episodes: int = 30) -> float:
    env = Monitor(MaxNeighbourEnv())
    env.reset(seed=1000)
    if model is None:
        rng = np.random.default_rng(0)
        total = []
        for episode in range(episodes):
            env.reset(seed=1000 + episode)
            for _ in range(8):
                total.append(env.step(rng.uniform(-1, 1, 8))[1])
        return -float(np.mean(total))
    mean_return, _ = evaluate_policy(model, env, n_eval_episodes=episodes)
    return -mean_return / 8  # 8 steps per episode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=2000, help="environment steps per algorithm")
    parser.add_argument("--algos", nargs="+", default=list(ALGOS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--ent-coef",
        default=None,
        help="ent_coef of SAC, TQC and CrossQ, e.g. auto_0.01 (default: SB3's, 'auto', which starts at 1.0)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [["random policy", "", f"{error_per_vertex(None):.3f}", ""]]
    for name in args.algos:
        kwargs = settings(name, args.ent_coef)
        model = getattr(sb3_graph, name)("GraphPolicy", MaxNeighbourEnv(), seed=args.seed, **kwargs)
        start = time.perf_counter()
        model.learn(args.steps)
        elapsed = time.perf_counter() - start
        error = error_per_vertex(model)
        rows.append([name, str(args.steps), f"{error:.3f}", f"{elapsed:.0f}"])
        print(f"{name}: error {error:.3f}, {elapsed:.0f} s", flush=True)
    coef = f", ent_coef {args.ent_coef} (SAC, TQC, CrossQ)" if args.ent_coef else ""
    print(f"\n## Toy graph task (GraphMaxNeighbour-v0), seed {args.seed}{coef}\n")
    print(machine_line() + "\n")
    print(markdown_table(["algorithm", "env steps", "mean absolute error per vertex", "wall time [s]"], rows))


if __name__ == "__main__":
    main()
