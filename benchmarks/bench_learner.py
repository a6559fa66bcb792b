"""Learner speed: gradient steps per second of every algorithm with its graph policy vs ``MlpPolicy``.

Same data for both learners of an algorithm. ``--data intersection`` (default): 2,000 transitions
of the intersection environment as the paper's config trains on it (``CoopIntersection4Way-v0``
with ``zoo_configs/td3_fair.yml``'s traffic, driven by its pretrained planner with the config's
action noise; about 15 vehicles and 62 edges per observation, 4,352 flattened inputs, see
``IntersectionRecording``). ``--data features``: the same with the shipped planner's config
(``zoo_configs/td3_residual_features.yml``: the residual action behind the shield, 11 features per
vehicle and 2 per edge, which its convolutions read; about 21 vehicles and 131 edges, 6,912
flattened inputs). ``--data random``: random paper-scale graphs (~20 vertices, ~60 edges). All in a
``GraphSpace(max_nodes=64, max_edges=1024)``; the MLP sees the padded observation flattened with
hidden layers [64, 64] (CrossQ's too, instead of its default [256, 256] / [1024, 1024]; TQC's 25
quantiles per critic for both); the graph networks use hidden size 64 (defaults). Batch 256 for the
off-policy algorithms, from a replay buffer of 2,000 transitions. PPO: one epoch over a rollout of
2,048 transitions in minibatches of 256 (a "step" is one minibatch update). The graph learners use
the graph buffers (ragged storage); the MLP learners SB3's buffers. Per algorithm, three learners
are timed in turns (best of 3 runs each), so that a change of the machine's load hits all of them:
the graph learner; the reference, the learner before issue #27 (``use_compiled_kernels(False)``:
the PyTorch formulation; torch's per-tensor Adam; SB3's own ``train``, whose policy loss also
differentiates the critics' weights); and the MLP learner. Then ``--paired-rounds`` rounds of the graph
and the MLP learner back to back (random order, 4 training calls each; the median and quartiles of
the per-round ratio of their times per step). Target (TD3): the graph learner within 1.5x of the
MLP learner. Also times the TD3 graph learner with 1 and 2 torch threads
(``--threads``); ``--profile`` adds the operator breakdown of the TD3 and SAC graph learners
(torch.profiler, self CPU time of 10 gradient steps).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import stable_baselines3
import torch
from graph_bench_utils import (
    MAX_NODES,
    IntersectionRecording,
    PaperScaleGraphEnv,
    _null_logger,
    fill,
    interleaved_rates,
    machine_line,
    markdown_table,
    per_tensor_optimizers,
    threads_table,
)
from gymnasium.spaces.utils import flatten, flatten_space
from gymnasium.wrappers import FlattenObservation

import sb3_graph
from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.layers import use_compiled_kernels

FILL = 2000
ROLLOUT = 2048
BATCH = 256
OFF_POLICY = ("TD3", "DDPG", "SAC", "TQC", "CrossQ")
ON_POLICY = ("PPO",)


class RandomGraphs:
    """Random paper-scale graphs with the interface of ``IntersectionRecording``."""

    def __init__(self) -> None:
        self._env = PaperScaleGraphEnv()

    def env(self) -> PaperScaleGraphEnv:
        return self._env

    def fill(self, buffers: list, transform: Callable | None = None) -> None:
        fill(buffers, self._env, FILL, transform=transform)

    def mean_size(self) -> tuple[float, float]:
        return 20.0, 60.0


def training_call(model) -> tuple:
    """A call that trains ``model`` and the number of gradient steps (minibatch updates) it makes."""
    model.set_logger(_null_logger())
    if hasattr(model, "rollout_buffer"):  # one epoch over the rollout: ROLLOUT / BATCH updates
        return model.train, ROLLOUT // BATCH
    return (lambda: model.train(gradient_steps=2, batch_size=BATCH)), 2


def sb3_train_call(model) -> Callable:
    """A call that trains ``model`` with SB3's own ``train``, without what the graph algorithms add
    around it (the critics' weights stay in the policy loss's autograd graph)."""
    model.set_logger(_null_logger())
    if hasattr(model, "rollout_buffer"):
        return lambda: super(GraphAlgorithmMixin, model).train()
    return lambda: super(GraphAlgorithmMixin, model).train(gradient_steps=2, batch_size=BATCH)


def reference_call(call: Callable, model=None) -> Callable:
    """``call`` with the compiled kernels off (the PyTorch formulation of the relational layers)
    and, for an off-policy ``model``, torch's per-tensor Adam (the graph policies' optimizers
    default to ``foreach=True`` since the third round)."""

    def run() -> None:
        previous = use_compiled_kernels(False)
        try:
            if model is not None and hasattr(model, "critic"):
                with per_tensor_optimizers(model):
                    call()
            else:
                call()
        finally:
            use_compiled_kernels(previous)

    return run


def steps_per_second(
    models: list,
    min_seconds: float,
    reference: tuple[int, ...] = (),
    repeats: int = 3,
    clock=time.perf_counter,
) -> list[float]:
    """Gradient steps per second of each model, timed in turns (see ``interleaved_rates``); the
    models at the positions in ``reference`` run as the learner before issue #27 (compiled kernels
    off, SB3's own ``train``)."""
    calls = [training_call(m) for m in models]
    functions = []
    for k, (call, _) in enumerate(calls):
        if k in reference:
            call = reference_call(sb3_train_call(models[k]), models[k])
        functions.append(call)
    rates = interleaved_rates(functions, min_seconds, repeats, clock)
    return [r * steps for r, (_, steps) in zip(rates, calls)]


def fill_rollout(buffer, env, transform=None) -> None:
    """A full rollout of the data's graphs, random actions (0 in padded slots), values and log-probabilities."""
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


def make_learners(name: str, data) -> tuple:
    """The graph learner and the MlpPolicy learner of one algorithm, their buffers filled with the
    same transitions."""
    env = data.env()
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
    data.fill([graph.replay_buffer])
    data.fill([mlp.replay_buffer], transform=transform)
    return graph, mlp


def paired_ratios(graph, mlp, rounds: int, clock=time.process_time) -> list[float]:
    """Per round, the graph learner's time per gradient step over the MLP learner's, the two timed
    back to back in random order (4 training calls each): unlike the ratio of two best rates, a
    load change or a slow stretch of this process hits both halves of a round alike."""
    calls = [training_call(graph), training_call(mlp)]
    rng = np.random.default_rng(0)
    ratios = []
    for _ in range(rounds):
        seconds = [0.0, 0.0]
        for k in rng.permutation(2):
            call, steps = calls[k]
            start = clock()
            for _ in range(4):
                call()
            seconds[k] = (clock() - start) / (4 * steps)
        ratios.append(seconds[0] / seconds[1])
    return ratios


def profile_table(model, steps: int = 10, rows: int = 14) -> str:
    """Markdown table of the operators with the most self CPU time over ``steps`` gradient steps."""
    from torch.profiler import ProfilerActivity, profile

    model.train(gradient_steps=2, batch_size=BATCH)  # warm-up
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        model.train(gradient_steps=steps, batch_size=BATCH)
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
    parser.add_argument(
        "--data",
        choices=("intersection", "features", "random"),
        default="intersection",
        help="transitions: td3_fair.yml's intersection, td3_residual_features.yml's (the shipped planner's), random",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timing runs per learner (the best counts)")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall", help="wall time or this process's CPU time")
    parser.add_argument("--threads", action="store_true", help="also time the TD3 graph learner with 1 and 2 threads")
    parser.add_argument("--profile", action="store_true", help="print the TD3 and SAC graph learners' operators")
    parser.add_argument(
        "--paired-rounds",
        type=int,
        default=20,
        help="rounds of the paired ratio: graph and MLP learner back to back, in random order (0: none)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.data == "random":
        data = RandomGraphs()
    else:
        data = IntersectionRecording(FILL, recording="fair" if args.data == "intersection" else "features")
    rows = []
    for name in args.algos:
        graph, mlp = make_learners(name, data)
        clock = time.process_time if args.clock == "cpu" else time.perf_counter
        ours, reference, mlp_rate = steps_per_second(
            [graph, graph, mlp], args.seconds, reference=(1,), repeats=args.repeats, clock=clock
        )
        paired = "-"
        if args.paired_rounds:
            ratios = paired_ratios(graph, mlp, args.paired_rounds, clock)
            quartiles = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else ratios * 3
            paired = f"{statistics.median(ratios):.2f} ({quartiles[0]:.2f}-{quartiles[2]:.2f})"
        rows.append(
            [name, f"{ours:.1f}", f"{reference:.1f}", f"{ours / reference:.2f}", f"{mlp_rate:.1f}",
             f"{mlp_rate / ours:.2f}", paired, f"{mlp_rate / reference:.2f}"]
        )  # fmt: skip
        rates = f"graph {ours:.1f} (reference {reference:.1f}), MLP {mlp_rate:.1f}"
        print(f"{name}: {rates} steps/s", flush=True)
    nodes, edges = data.mean_size()
    inputs = flatten_space(data.env().observation_space).shape[0]
    print(f"\n## Learner speed ({args.data} data: {nodes:.1f} vertices / {edges:.1f} edges per graph; batch {BATCH}, ")
    print(f"hidden 64, 1 torch thread; steps per {args.clock} second)\n\n{machine_line()}\n")
    header = [
        "algorithm",
        "graph policy, steps/s",
        "graph, PyTorch reference, steps/s",
        "speed-up vs reference",
        f"MlpPolicy [64, 64] on {inputs} inputs, steps/s",
        "x slower than MLP",
        "paired: x slower than MLP, median (IQR)",
        "reference: x slower than MLP",
    ]
    print(markdown_table(header, rows))
    if args.threads:
        print("\n" + threads_table(args.seconds))
    if args.profile:
        for name in ("TD3", "SAC"):
            graph, _ = make_learners(name, data)
            graph.set_logger(_null_logger())
            for label, enabled in (("compiled kernels", True), ("PyTorch reference", False)):
                previous = use_compiled_kernels(enabled)
                print(f"\n## {name} graph learner profile, {label} (top operators by self CPU time)\n")
                print(profile_table(graph))
                use_compiled_kernels(previous)


if __name__ == "__main__":
    main()
