"""Cost of a tuning trial: environment steps per second of TD3's training loop, end to end.

Each variant builds the learner exactly as ``sb3-graph train`` / ``sb3-graph tune`` do, from the
entry of ``zoo_configs/td3.yml`` (policy, graph replay buffer, curriculum callback, noise) with
the variant's changes, and times ``model.learn``: environment steps, action selection, replay
buffer, gradient steps, callbacks. Only the learning phase is timed (from ``learning_starts`` on;
before it no gradient step runs). Variants run in turns, ``--rounds`` times, and the median is
reported, so that a change of the shared machine's load hits all of them.

Variants (``today`` is the entry as it is; the others change one thing at a time, then combine):

- ``today``: full environment (60 s episodes, 64 vehicle slots), 1 env, ``train_freq 1``,
  ``gradient_steps 1``: one gradient step per environment step.
- ``preset``: the reduced "tuning" environment of ``envs.evaluation.tuning`` (20 s, 16 slots, 192 edges).
- ``freq4``: ``train_freq 4, gradient_steps 4``: the same gradient steps per environment step,
  in fewer, larger calls of ``train``.
- ``utd½``: ``train_freq 2, gradient_steps 1``: half the gradient steps per environment step
  (changes the algorithm: its quality must be checked with a study, not assumed).
- ``2envs``: two environments (``DummyVecEnv``), ``gradient_steps 2`` per vector step: the
  same updates per transition, batched action selection.
- ``2envs-subproc``: the same with ``SubprocVecEnv`` (environments in 2 processes).
- ``preset+utd½+2envs``: the combination.

``--critic-pass`` instead times ``TD3.train`` with the twin critics one after the other (today)
and in one batched pass; ``--profile`` shows where today's ``learn`` spends its time.

Prints a markdown table: env steps per wall second and per CPU second of the learner process
(medians over rounds), each with its ratio to ``today``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from graph_bench_utils import machine_line, markdown_table
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import envs  # noqa: F401 - registers the environments
from envs.evaluation.tuning import tuning_env_kwargs
from sb3_graph import TD3
from sb3_graph.files.experiment_files import (
    build_algorithm_kwargs,
    build_callbacks,
    check_entry,
    merge_env_kwargs,
    read_experiment,
    resolve_object,
)

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "CoopIntersection4Way-v0"
PRESET = {"env_kwargs": tuning_env_kwargs()}
VARIANTS = {
    "today": {},
    "preset": PRESET,
    "freq4": {"train_freq": 4, "gradient_steps": 4},
    "utd½": {"train_freq": 2, "gradient_steps": 1},
    "2envs": {"n_envs": 2, "gradient_steps": 2},
    "2envs-subproc": {"n_envs": 2, "gradient_steps": 2, "vec_env": SubprocVecEnv},
    "preset+utd½+2envs": {**PRESET, "n_envs": 2, "train_freq": 1, "gradient_steps": 1},
}


class LearningClock(BaseCallback):
    """Steps per wall second and per CPU second of this process, from ``learning_starts`` to the end.

    On a shared, loaded machine the wall rate says as much about the neighbours as about the code;
    the CPU rate (``time.process_time``, one torch thread) is what an idle core would give, but it
    misses the work of ``SubprocVecEnv``'s environment processes (reported as NaN there).
    """

    def __init__(self, learning_starts: int, count_cpu: bool = True) -> None:
        super().__init__()
        self.learning_starts = learning_starts
        self.count_cpu = count_cpu
        self.start: tuple[float, float, int] | None = None
        self.rate = self.cpu_rate = float("nan")

    def _on_step(self) -> bool:
        if self.start is None and self.num_timesteps >= self.learning_starts:
            self.start = (time.perf_counter(), time.process_time(), self.num_timesteps)
        return True

    def _on_training_end(self) -> None:
        wall, cpu, steps = time.perf_counter(), time.process_time(), self.num_timesteps - self.start[2]
        self.rate = steps / (wall - self.start[0])
        if self.count_cpu:
            self.cpu_rate = steps / (cpu - self.start[1])


def steps_per_second(base: dict, change: dict, steps: int, learning_starts: int, seed: int) -> tuple[float, float]:
    """Env steps per wall second and per CPU second of one learning run of ``base`` with ``change`` applied."""
    change = dict(change)
    vec_env_cls = change.pop("vec_env", DummyVecEnv)
    entry = dict(base)
    entry["env_kwargs"] = merge_env_kwargs(entry.get("env_kwargs") or {}, change.pop("env_kwargs", {}))
    entry.update(change, learning_starts=learning_starts)
    n_envs = int(entry.get("n_envs", 1))
    env = make_vec_env(ENV_ID, n_envs=n_envs, seed=seed, env_kwargs=entry["env_kwargs"], vec_env_cls=vec_env_cls)
    try:
        policy = resolve_object(entry["policy"], "policy")
        model = TD3(policy, env, seed=seed, device="cpu", **build_algorithm_kwargs(entry, env.action_space.shape[0]))
        clock = LearningClock(learning_starts, count_cpu=vec_env_cls is not SubprocVecEnv)
        model.learn(learning_starts + steps, callback=CallbackList([*build_callbacks(entry), clock]))
    finally:
        env.close()
    return clock.rate, clock.cpu_rate


def profile_today(base: dict, steps: int, learning_starts: int) -> None:
    """Where the time of ``today``'s ``learn`` goes (cProfile, cumulative time of the parts)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.runcall(steps_per_second, base, {}, steps, learning_starts, 0)
    stats = pstats.Stats(profiler).stats  # (file, line, function) -> (calls, ..., cumulative s, callers)
    parts = {
        "gradient steps (TD3.train)": ("td3.py", "train"),
        "action selection (_sample_action)": ("off_policy_algorithm.py", "_sample_action"),
        "environment (VecEnv.step)": ("base_vec_env.py", "step"),
        "whole learn()": ("off_policy_algorithm.py", "learn"),
    }
    seconds = {
        name: max((v[3] for (f, _, fn), v in stats.items() if f.endswith(file) and fn == func), default=0.0)
        for name, (file, func) in parts.items()
    }
    total = seconds["whole learn()"] or 1.0
    print(f"profile of 'today' ({learning_starts} + {steps} steps), cumulative time:")
    for name, value in seconds.items():
        print(f"  {name}: {value:.1f} s ({100 * value / total:.0f} %)")


def critic_pass_rates(base: dict, rounds: int, gradient_steps: int = 30) -> dict[str, list[float]]:
    """Gradient steps per CPU second of ``TD3.train`` with the twin critics run one after the other
    (``GraphCritic.forward`` today) or in one batched pass (``stacked_q_forward``), in turns on the
    same model and replay buffer (filled by 400 steps of the full environment)."""
    from stable_baselines3.common.logger import configure

    from sb3_graph.common.networks import GraphCritic, as_graph_batch, gather_vertex_values, stacked_q_forward

    def batched(self, obs, actions):
        graphs = as_graph_batch(obs)
        return tuple(stacked_q_forward(self.q_networks, graphs, gather_vertex_values(actions, graphs)).unbind(0))

    entry = {**base, "learning_starts": 400}
    env = make_vec_env(ENV_ID, n_envs=1, seed=0, env_kwargs=entry["env_kwargs"])
    model = TD3(resolve_object(entry["policy"], "policy"), env, seed=0, device="cpu",
                **build_algorithm_kwargs(entry, env.action_space.shape[0]))  # fmt: skip
    model.learn(400)
    model.set_logger(configure(None, [""]))
    today = GraphCritic.forward
    rates: dict[str, list[float]] = {"one critic at a time": [], "batched pass": []}
    try:
        for _ in range(rounds):
            for name, forward in zip(rates, (today, batched)):
                GraphCritic.forward = forward
                tic = time.process_time()
                model.train(gradient_steps=gradient_steps, batch_size=int(entry["batch_size"]))
                rates[name].append(gradient_steps / (time.process_time() - tic))
    finally:
        GraphCritic.forward = today
        env.close()
    return rates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500, help="timed environment steps per run")
    parser.add_argument("--learning-starts", type=int, default=500, help="untimed steps that fill the buffer")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each variant, in turns (median)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--profile", action="store_true", help="only profile 'today' (where its time goes)")
    parser.add_argument(
        "--critic-pass", action="store_true", help="only compare the twin critics one at a time vs batched"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base = check_entry(read_experiment(ROOT / "zoo_configs" / "td3.yml", ENV_ID))
    if args.critic_pass:
        rates = critic_pass_rates(base, max(args.rounds, 3))
        rows = [[name, f"{statistics.median(r):.1f}", " / ".join(f"{x:.1f}" for x in r)] for name, r in rates.items()]
        print(markdown_table(["twin critics", "gradient steps per CPU s (median)", "each round"], rows))
        print(machine_line())
        return
    if args.profile:
        profile_today(base, args.steps, args.learning_starts)
        print(machine_line())
        return
    rates: dict[str, list[tuple[float, float]]] = {name: [] for name in args.variants}
    for round_ in range(args.rounds):
        for name in args.variants:
            wall, cpu = steps_per_second(base, VARIANTS[name], args.steps, args.learning_starts, seed=round_)
            rates[name].append((wall, cpu))
            print(f"round {round_}: {name}: {wall:.1f} env steps/s, {cpu:.1f} per CPU second", flush=True)
    median = {name: [statistics.median(r[i] for r in runs) for i in (0, 1)] for name, runs in rates.items()}
    today = median.get("today", [float("nan")] * 2)
    rows = [
        [name, f"{wall:.1f}", f"{wall / today[0]:.2f}x", f"{cpu:.1f}", f"{cpu / today[1]:.2f}x"]
        for name, (wall, cpu) in median.items()
    ]
    header = ["variant", "env steps/s (wall)", "vs today", "env steps per CPU s", "vs today"]
    print(markdown_table(header, rows))
    print(f"medians over {args.rounds} round(s); wall rates on a loaded machine mostly measure the load")
    print(f"{args.steps} timed steps after {args.learning_starts} per run, {args.threads} torch thread(s)")
    print(machine_line())
    if not np.isfinite(today[0]):
        print("(no 'today' variant: no ratio)")


if __name__ == "__main__":
    main()
