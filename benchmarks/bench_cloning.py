"""Behaviour cloning on the intersection: wall time of collecting demonstrations and of the gradient steps,
and how often the cloned policy agrees with its expert.

Builds the learner of a zoo config (default ``zoo_configs/td3_shield.yml``: TD3 behind the shield, 4
environments, encoder 64, two convolutions of 64), clones a planner (default AIM) with
``sb3_graph.behaviour_clone`` and reports, one torch thread:

- seconds per collected transition (the planner and the environments) and per gradient step of the
  actor and of the critics' warm-up, and the extrapolation to the issue's budget (10,000 transitions,
  2,000 actor steps, 500 critic steps);
- with ``--agreement-steps K``: over ``K`` fresh steps of the training environments driven by the
  cloned policy, the share of vehicle-steps whose action lies within 0.1 of the expert's (both in the
  action space's units, [-1, 1]), and the same share for the untrained policy;
- with ``--save PATH``: the cloned model, for ``sb3-graph export`` and ``sb3-graph evaluate`` (flow,
  delay and stops against the expert on validation scenarios).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from graph_bench_utils import machine_line, markdown_table
from stable_baselines3.common.env_util import make_vec_env

import envs  # noqa: F401  (registers the environments)
from envs.planners.expert import PlannerExpert
from sb3_graph.common.cloning import behaviour_clone
from sb3_graph.files.experiment_files import build_algorithm_kwargs, read_experiment
from sb3_graph.registry import ALGORITHMS

ISSUE_BUDGET = (10_000, 2_000, 500)  # transitions, actor steps, critic steps


def agreement(model, expert: PlannerExpert, env, steps: int) -> float:
    """Share of real vehicle-steps where the policy's deterministic action is within 0.1 of the expert's."""
    obs = env.reset()
    close = total = 0
    for _ in range(steps):
        wanted = expert(obs)
        action, _ = model.predict(obs, deterministic=True)
        real = obs["node_mask"].astype(bool)
        close += int((np.abs(action - wanted)[real] <= 0.1).sum())
        total += int(real.sum())
        obs, _, _, _ = env.step(action)
    return close / max(total, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--config", default="zoo_configs/td3_shield.yml")
    parser.add_argument("--env", default="CoopIntersection4Way-v0")
    parser.add_argument("--algo", default="td3", choices=list(ALGORITHMS))
    parser.add_argument("--planner", default="aim")
    parser.add_argument("--transitions", type=int, default=1000)
    parser.add_argument("--gradient-steps", type=int, default=200)
    parser.add_argument("--critic-steps", type=int, default=50)
    parser.add_argument("--agreement-steps", type=int, default=0)
    parser.add_argument("--save", default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    entry = read_experiment(args.config, args.env)
    n_envs = int(entry.get("n_envs", 1))
    env = make_vec_env(args.env, n_envs=n_envs, seed=args.seed, env_kwargs=entry.get("env_kwargs"))
    kwargs = build_algorithm_kwargs(entry, int(np.prod(env.action_space.shape)))
    model = ALGORITHMS[args.algo].load_class()("GraphPolicy", env, seed=args.seed, **kwargs)
    expert = PlannerExpert(args.planner, env)
    rows = []
    if args.agreement_steps:
        start = time.perf_counter()
        share = agreement(model, PlannerExpert(args.planner, env), env, args.agreement_steps)
        rows.append(["untrained policy: actions within 0.1 of the expert's", f"{share:.1%}"])
        print(f"untrained agreement {share:.3f} ({time.perf_counter() - start:.0f} s)", flush=True)
    result = behaviour_clone(
        model,
        expert,
        transitions=args.transitions,
        gradient_steps=args.gradient_steps,
        batch_size=int(entry.get("batch_size", 256)),
        critic_steps=args.critic_steps,
    )
    actor_s = result["train_s"] / max(args.gradient_steps, 1)
    critic_s = result["critic_s"] / max(args.critic_steps, 1)
    per_transition = result["collect_s"] / result["transitions"]
    n, g, c = ISSUE_BUDGET
    total = per_transition * n + actor_s * g + critic_s * c
    rows += [
        ["transitions collected", f"{result['transitions']} in {result['collect_s']:.1f} s"],
        ["per transition (planner + environments)", f"{per_transition * 1e3:.1f} ms"],
        ["actor gradient step", f"{actor_s * 1e3:.0f} ms"],
        ["critic warm-up step", f"{critic_s * 1e3:.0f} ms"],
        ["actor loss first -> last", f"{result['actor_loss'][0]:.4f} -> {result['actor_loss'][-1]:.4f}"],
        [f"issue budget ({n} transitions, {g} actor + {c} critic steps), extrapolated", f"{total / 60:.1f} min"],
    ]
    if args.agreement_steps:
        share = agreement(model, PlannerExpert(args.planner, env), env, args.agreement_steps)
        rows.append(["cloned policy: actions within 0.1 of the expert's", f"{share:.1%}"])
    if args.save:
        model.save(args.save)
    print(f"\n## Cloning {args.planner} into {args.algo} ({args.config}, {args.env}), seed {args.seed}\n")
    print(machine_line() + "\n")
    print(markdown_table(["quantity", "value"], rows))


if __name__ == "__main__":
    main()
