"""Learner speed: gradient steps per second of every algorithm with its graph policy vs ``MlpPolicy``.

Same data for both learners of an algorithm: random paper-scale graphs (~20 vertices, ~60 edges)
in a ``GraphSpace(max_nodes=64, max_edges=1024)``; the MLP sees the padded observation flattened
(4,352 inputs) with hidden layers [64, 64] (CrossQ's too, instead of its default [256, 256] /
[1024, 1024]; TQC's 25 quantiles per critic for both); the graph networks use hidden size 64
(defaults). Batch 256 for the off-policy algorithms, from a replay buffer of 2,000 transitions.
PPO: one epoch over a rollout of 2,048 transitions in minibatches of 256 (a "step" is one
minibatch update). The graph learners use the graph buffers (ragged storage); the MLP learners
SB3's buffers. The two learners of an algorithm are timed in turns (best of 3 runs each), so that
a change of the machine's load hits both. Target (TD3): the graph learner within 5x of the MLP
learner. Also times the TD3
graph learner with 1 and 2 torch threads; ``--profile`` adds its operator breakdown
(torch.profiler, self CPU time of 10 gradient steps).
"""

from __future__ import annotations

import argparse

import numpy as np
import stable_baselines3
import torch
from graph_bench_utils import (
    MAX_NODES,
    PaperScaleGraphEnv,
    _null_logger,
    fill,
    interleaved_rates,
    machine_line,
    markdown_table,
    threads_table,
)
from gymnasium.spaces.utils import flatten, flatten_space
from gymnasium.wrappers import FlattenObservation

import sb3_graph
from sb3_graph import TD3, GraphPolicy

FILL = 2000
ROLLOUT = 2048
BATCH = 256
OFF_POLICY = ("TD3", "DDPG", "SAC", "TQC", "CrossQ")
ON_POLICY = ("PPO",)


def training_call(model) -> tuple:
    """A call that trains ``model`` and the number of gradient steps (minibatch updates) it makes."""
    model.set_logger(_null_logger())
    if hasattr(model, "rollout_buffer"):  # one epoch over the rollout: ROLLOUT / BATCH updates
        return model.train, ROLLOUT // BATCH
    return (lambda: model.train(gradient_steps=2, batch_size=BATCH)), 2


def steps_per_second(models: list, min_seconds: float) -> list[float]:
    """Gradient steps per second of each model, timed in turns (see ``interleaved_rates``)."""
    calls = [training_call(m) for m in models]
    rates = interleaved_rates([call for call, _ in calls], min_seconds)
    return [r * steps for r, (_, steps) in zip(rates, calls)]


def fill_rollout(buffer, env: PaperScaleGraphEnv, transform=None) -> None:
    """A full rollout of random graphs, actions (0 in padded slots), values and log-probabilities."""
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for step in range(buffer.buffer_size):
        obs = env.graph()
        action = rng.standard_normal((1, MAX_NODES)).astype(np.float32) * obs["node_mask"]
        stored = transform(obs)[None] if transform else {k: v[None] for k, v in obs.items()}
        buffer.add(
            stored, action, rng.standard_normal(1), np.array([step % 100 == 0]), torch.randn(1, 1), torch.randn(1)
        )
    buffer.compute_returns_and_advantage(torch.zeros(1, 1), np.array([False]))


def make_learners(name: str, env: PaperScaleGraphEnv) -> tuple:
    """The graph learner and the MlpPolicy learner of one algorithm, their buffers filled with the
    same transitions."""
    graph_class = getattr(sb3_graph, name)
    stock = getattr(stable_baselines3, name, None) or getattr(__import__("sb3_contrib"), name)
    flat_env = FlattenObservation(env)
    space = env.observation_space
    transform = lambda o: flatten(space, o).astype(np.float32)  # noqa: E731
    if name in ON_POLICY:
        kwargs = dict(n_steps=ROLLOUT, batch_size=BATCH, n_epochs=1, seed=0)
        graph = graph_class("GraphPolicy", env, **kwargs)
        mlp = stock("MlpPolicy", flat_env, policy_kwargs=dict(net_arch=[64, 64]), **kwargs)
        fill_rollout(graph.rollout_buffer, env)
        fill_rollout(mlp.rollout_buffer, env, transform)
        return graph, mlp
    graph = graph_class("GraphPolicy", env, buffer_size=FILL, batch_size=BATCH, seed=0)
    mlp = stock("MlpPolicy", flat_env, buffer_size=FILL, seed=0, policy_kwargs=dict(net_arch=[64, 64]))
    fill([graph.replay_buffer], env, FILL)
    fill([mlp.replay_buffer], env, FILL, transform=transform)
    return graph, mlp


def profile_table(model, steps: int = 10, rows: int = 12) -> str:
    """Markdown table of the operators with the most self CPU time over ``steps`` gradient steps."""
    from torch.profiler import ProfilerActivity, profile

    model.train(gradient_steps=2, batch_size=256)  # warm-up
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        model.train(gradient_steps=steps, batch_size=256)
    events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events)
    lines = []
    for event in events[:rows]:
        ms, share = event.self_cpu_time_total / 1e3 / steps, 100 * event.self_cpu_time_total / total
        lines.append([event.key, f"{ms:.2f}", f"{share:.0f}", str(event.count)])
    lines.append(["total", f"{total / 1e3 / steps:.2f}", "100", ""])
    return markdown_table(["operator", "self CPU ms per step", "%", "calls"], lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.0, help="minimum seconds per timing run")
    parser.add_argument("--algos", nargs="+", default=[*OFF_POLICY, *ON_POLICY], help="algorithms to time")
    parser.add_argument("--skip-threads", action="store_true", help="skip the 1 vs 2 threads timing")
    parser.add_argument("--profile", action="store_true", help="print the TD3 graph learner's operator breakdown")
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = PaperScaleGraphEnv()
    rows = []
    for name in args.algos:
        graph_rate, mlp_rate = steps_per_second(list(make_learners(name, env)), args.seconds)
        rows.append([name, f"{graph_rate:.1f}", f"{mlp_rate:.1f}", f"{mlp_rate / graph_rate:.1f}"])
        print(f"{name}: graph {graph_rate:.1f}, MLP {mlp_rate:.1f} steps/s", flush=True)
    if "TD3" in args.algos:
        graph = TD3("GraphPolicy", env, buffer_size=FILL, batch_size=BATCH, seed=0)
        graph_dict = stable_baselines3.TD3(GraphPolicy, env, buffer_size=FILL, seed=0)
        fill([graph.replay_buffer, graph_dict.replay_buffer], env, FILL)
        ours, padded = steps_per_second([graph, graph_dict], args.seconds)
        rows.append(["TD3, graph policy + GraphReplayBuffer (timed in turns with the next row)", f"{ours:.1f}", "", ""])
        rows.append(["TD3, graph policy + SB3's padded DictReplayBuffer", f"{padded:.1f}", "", ""])
    inputs = flatten_space(env.observation_space).shape[0]
    print(f"\n## Learner speed (batch {BATCH}, ~20 vertices / ~60 edges, hidden 64, 1 torch thread)\n")
    print(machine_line() + "\n")
    header = [
        "algorithm",
        "graph policy, steps/s",
        f"MlpPolicy [64, 64] on {inputs} inputs, steps/s",
        "x slower than MLP",
    ]
    print(markdown_table(header, rows))
    if not args.skip_threads:
        print("\n" + threads_table(args.seconds))
    if args.profile:
        print("\n## TD3 graph learner profile (1 torch thread, top operators by self CPU time)\n")
        torch.set_num_threads(1)
        graph = TD3("GraphPolicy", env, buffer_size=FILL, batch_size=BATCH, seed=0)
        fill([graph.replay_buffer], env, FILL)
        print(profile_table(graph))


if __name__ == "__main__":
    main()
