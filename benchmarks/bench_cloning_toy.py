"""Cloning against RL on the toy graph task: error per vertex after cloning the exact answer with N gradient
steps, after RL alone, and after RL on top of the clone (with and without the ``bc_coef`` regularizer).

The task and the settings are those of ``bench_toy_task.py`` (``GraphMaxNeighbour-v0``, encoder 32,
two convolutions of 32, ``gamma=0``, untuned settings; error over 30 evaluation episodes; a random
policy: ~0.57). The expert is the task's exact answer (``sb3_graph.toy_envs.max_neighbour_expert``);
cloning collects ``--transitions`` demonstrations (1 environment) and takes N gradient steps of batch
64 (off-policy: plus N // 4 critic warm-up steps). RL alone runs ``--rl-steps`` environment steps, RL on
top of the clone ``--rl-after`` (default: the same). Every model is scored on the same 30 evaluation
episodes. RL gradient steps are SB3's updates: one critic step per environment step after
``learning_starts`` off-policy, ``n_epochs`` passes of minibatches per rollout for PPO. One torch thread.
"""

from __future__ import annotations

import argparse
import time

import torch
from bench_toy_task import error_per_vertex, settings
from graph_bench_utils import machine_line, markdown_table

import sb3_graph
from sb3_graph.toy_envs import MaxNeighbourEnv, max_neighbour_expert


def cloned(name: str, seed: int, transitions: int, steps: int, **extra):
    model = getattr(sb3_graph, name)("GraphPolicy", MaxNeighbourEnv(), seed=seed, **settings(name), **extra)
    start = time.perf_counter()
    sb3_graph.behaviour_clone(model, max_neighbour_expert, transitions=transitions, gradient_steps=steps, batch_size=64)
    return model, time.perf_counter() - start


def rl_gradient_steps(model) -> int:
    """Gradient steps of ``model``'s RL so far (SB3 counts PPO's epochs, not its minibatches)."""
    if hasattr(model, "n_epochs"):
        return model._n_updates * (model.n_steps * model.n_envs // model.batch_size)
    return model._n_updates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--algos", nargs="+", default=["TD3", "SAC", "PPO"])
    parser.add_argument("--transitions", type=int, default=1000)
    parser.add_argument("--clone-steps", type=int, nargs="+", default=[50, 200, 500])
    parser.add_argument("--rl-steps", type=int, default=5000, help="environment steps of RL from scratch")
    parser.add_argument("--rl-after", type=int, default=None, help="environment steps of RL on top of the clone")
    parser.add_argument("--bc-coef", type=float, default=0.5, help="bc_coef of the regularized RL on top")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rl_after = args.rl_steps if args.rl_after is None else args.rl_after
    torch.set_num_threads(1)
    header = ["algorithm", "training", "env steps", "gradient steps (cloning)", "gradient steps (RL)",
              "error per vertex", "wall time [s]"]  # fmt: skip
    rows = [["random policy", "", "", "", "", f"{error_per_vertex(None):.3f}", ""]]
    for name in args.algos:
        for steps in args.clone_steps:
            model, elapsed = cloned(name, args.seed, args.transitions, steps)
            error = error_per_vertex(model)
            rows.append([name, "cloning", str(args.transitions), str(steps), "", f"{error:.3f}", f"{elapsed:.0f}"])
            print(rows[-1], flush=True)
        if args.rl_steps:  # the reference: RL from scratch
            model = getattr(sb3_graph, name)("GraphPolicy", MaxNeighbourEnv(), seed=args.seed, **settings(name))
            start = time.perf_counter()
            model.learn(args.rl_steps)
            rows.append([name, "RL only", str(args.rl_steps), "", str(rl_gradient_steps(model)),
                         f"{error_per_vertex(model):.3f}", f"{time.perf_counter() - start:.0f}"])  # fmt: skip
            print(rows[-1], flush=True)
        if rl_after:
            for coef in (0.0, args.bc_coef):
                model, elapsed = cloned(name, args.seed, args.transitions, max(args.clone_steps), bc_coef=coef)
                start, warm_up = time.perf_counter(), rl_gradient_steps(model)  # the critics' warm-up counts
                model.learn(rl_after)
                label = f"cloning, then RL (bc_coef {coef:g})"
                wall = elapsed + time.perf_counter() - start
                budget = f"{args.transitions} + {rl_after}"
                error = error_per_vertex(model)
                rows.append([name, label, budget, str(max(args.clone_steps)), str(rl_gradient_steps(model) - warm_up),
                             f"{error:.3f}", f"{wall:.0f}"])  # fmt: skip
                print(rows[-1], flush=True)
    print(f"\n## Cloning the toy task's exact answer (GraphMaxNeighbour-v0), seed {args.seed}\n")
    print(machine_line() + "\n")
    print(markdown_table(header, rows))


if __name__ == "__main__":
    main()
