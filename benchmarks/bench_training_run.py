"""A training run of a config, the learner of today and the one before issue #27, in turns.

Builds TD3 from ``--config`` (default ``zoo_configs/td3_fair.yml``, the paper's; the shipped
planner's is ``zoo_configs/td3_residual_features.yml``) as ``sb3-graph train`` does (policy, graph
replay buffer, action noise, callbacks, the config's traffic and ``n_envs`` environments in this
process), with ``learning_starts`` lowered so that a short run trains (the config's would leave a
3,000-step run without a gradient step), and times ``learn`` from ``learning_starts`` to the end:
environment steps, action selection, replay buffer and the config's gradient steps (``td3_fair.yml``:
one of batch 128 per environment step; with ``n_envs: 4``, one per four environment steps).
The reference is the learner before issue #27: ``sb3_graph.common.layers.use_compiled_kernels(False)`` (the
PyTorch formulation of the relational layers), torch's per-tensor Adam and SB3's own ``train``
(whose policy loss also differentiates the critics' weights). They alternate run by run
(``--rounds`` each, same seeds), so a change of the shared machine's load hits both; the table gives
medians of env steps per wall second and per CPU second of this process (one torch thread).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
from pathlib import Path

import torch
from bench_trial_cost import ENV_ID, LearningClock
from graph_bench_utils import machine_line, markdown_table, per_tensor_optimizers
from stable_baselines3.common.callbacks import CallbackList
from stable_baselines3.common.env_util import make_vec_env

import envs  # noqa: F401 - registers the environments
from sb3_graph import TD3
from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.layers import use_compiled_kernels
from sb3_graph.files.experiment_files import (
    build_algorithm_kwargs,
    build_callbacks,
    check_entry,
    read_experiment,
    resolve_object,
)

ROOT = Path(__file__).resolve().parents[1]


def run(entry: dict, steps: int, learning_starts: int, seed: int, compiled: bool) -> tuple[float, float]:
    """Env steps per wall second and per CPU second of one learning run."""
    entry = dict(entry, learning_starts=learning_starts)
    env = make_vec_env(ENV_ID, n_envs=int(entry.get("n_envs", 1)), seed=seed, env_kwargs=entry.get("env_kwargs") or {})
    previous = use_compiled_kernels(compiled)
    try:
        policy = resolve_object(entry["policy"], "policy")
        model = TD3(policy, env, seed=seed, device="cpu", **build_algorithm_kwargs(entry, env.action_space.shape[0]))
        if not compiled:  # SB3's own train, without what the graph algorithms add around it
            model.train = super(GraphAlgorithmMixin, model).train
        clock = LearningClock(learning_starts)
        # The reference runs torch's per-tensor Adam, as the graph policies did before issue #27.
        with contextlib.nullcontext() if compiled else per_tensor_optimizers(model):
            model.learn(learning_starts + steps, callback=CallbackList([*build_callbacks(entry), clock]))
    finally:
        use_compiled_kernels(previous)
        env.close()
    return clock.rate, clock.cpu_rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="timed environment steps per run")
    parser.add_argument("--learning-starts", type=int, default=500, help="untimed steps that fill the buffer")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each version, in turns (median)")
    parser.add_argument("--config", type=Path, default=ROOT / "zoo_configs" / "td3_fair.yml")
    args = parser.parse_args()
    torch.set_num_threads(1)
    entry = check_entry(read_experiment(args.config, ENV_ID))
    rates: dict[str, list[tuple[float, float]]] = {"PyTorch reference": [], "compiled kernels": []}
    for round_ in range(args.rounds):
        for name in rates:
            wall, cpu = run(entry, args.steps, args.learning_starts, seed=round_, compiled=name == "compiled kernels")
            rates[name].append((wall, cpu))
            print(f"round {round_}: {name}: {wall:.1f} env steps/s, {cpu:.1f} per CPU second", flush=True)
    median = {name: [statistics.median(r[i] for r in runs) for i in (0, 1)] for name, runs in rates.items()}
    before = median["PyTorch reference"]
    rows = [
        [name, f"{wall:.1f}", f"{wall / before[0]:.2f}x", f"{cpu:.1f}", f"{cpu / before[1]:.2f}x",
         f"{args.steps / wall:.0f}"]
        for name, (wall, cpu) in median.items()
    ]  # fmt: skip
    header = ["version", "env steps/s (wall)", "vs reference", "env steps per CPU s", "vs reference", "wall s per run"]
    print(markdown_table(header, rows))
    print(f"medians over {args.rounds} round(s); {args.steps} timed steps after {args.learning_starts} per run")
    print(machine_line())


if __name__ == "__main__":
    main()
