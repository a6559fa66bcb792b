"""Learner speed: TD3 gradient steps per second with GraphPolicy vs MlpPolicy.

Same data for both: random paper-scale graphs (~20 vertices, ~60 edges) in a
``GraphSpace(max_nodes=64, max_edges=1024)``; the MLP sees the padded observation flattened
(4,352 inputs) with hidden layers [64, 64]; the graph networks use hidden size 64 (defaults).
Batch 256. Target: the graph learner within 5x of the MLP learner. Also times the graph
learner with 1 and 2 torch threads; ``--profile`` adds the graph learner's operator breakdown
(torch.profiler, self CPU time of 10 gradient steps).
"""

from __future__ import annotations

import argparse

import numpy as np
import stable_baselines3
import torch
from graph_bench_utils import (
    PaperScaleGraphEnv,
    _null_logger,
    fill,
    machine_line,
    markdown_table,
    rate,
    threads_table,
)
from gymnasium.spaces.utils import flatten, flatten_space
from gymnasium.wrappers import FlattenObservation

from sb3_graph import TD3, GraphPolicy

FILL = 2000


def steps_per_second(model, min_seconds: float) -> float:
    model.set_logger(_null_logger())
    return rate(lambda: model.train(gradient_steps=2, batch_size=256), min_seconds) * 2


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
    parser.add_argument("--skip-threads", action="store_true", help="skip the 1 vs 2 threads timing")
    parser.add_argument("--profile", action="store_true", help="print the graph learner's operator breakdown")
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = PaperScaleGraphEnv()
    results = {}

    graph = TD3("GraphPolicy", env, buffer_size=FILL, batch_size=256, seed=0)
    fill([graph.replay_buffer], env, FILL)
    results["TD3 GraphPolicy + GraphReplayBuffer"] = steps_per_second(graph, args.seconds)

    graph_dict = stable_baselines3.TD3(GraphPolicy, env, buffer_size=FILL, seed=0)
    fill([graph_dict.replay_buffer], env, FILL)
    results["SB3 TD3 GraphPolicy + DictReplayBuffer"] = steps_per_second(graph_dict, args.seconds)

    flat_env = FlattenObservation(env)
    mlp = stable_baselines3.TD3("MlpPolicy", flat_env, buffer_size=FILL, seed=0, policy_kwargs=dict(net_arch=[64, 64]))
    space = env.observation_space
    fill([mlp.replay_buffer], env, FILL, transform=lambda o: flatten(space, o).astype(np.float32))
    results[f"TD3 MlpPolicy [64, 64] on flattened padded obs ({flatten_space(space).shape[0]} inputs)"] = (
        steps_per_second(mlp, args.seconds)
    )

    reference = list(results.values())[-1]
    rows = [[name, f"{value:.1f}", f"{reference / value:.1f}"] for name, value in results.items()]
    print("## Learner speed (batch 256, ~20 vertices / ~60 edges, hidden 64, 1 torch thread)\n")
    print(machine_line() + "\n")
    print(markdown_table(["learner", "gradient steps/s", "x slower than MLP"], rows))
    if not args.skip_threads:
        print("\n" + threads_table(args.seconds))
    if args.profile:
        print("\n## Graph learner profile (1 torch thread, top operators by self CPU time)\n")
        torch.set_num_threads(1)
        print(profile_table(graph))


if __name__ == "__main__":
    main()
