"""Replay memory per transition: GraphReplayBuffer vs SB3's DictReplayBuffer on the same GraphSpace.

Paper scale: max_nodes=64, max_edges=1024, ~20 vertices and ~60 edges per graph, episodes of 100
steps (a next observation that is the following observation is stored once). Target: >= 20x
smaller. Prints a markdown table, the extrapolated footprint of 1M transitions, and the graph
learner's speed with 1 vs 2 torch threads.
"""

from __future__ import annotations

import argparse

import torch
from graph_bench_utils import PaperScaleGraphEnv, fill, machine_line, markdown_table, threads_table
from stable_baselines3.common.buffers import DictReplayBuffer

from sb3_graph import GraphReplayBuffer


def live_bytes(buffer: GraphReplayBuffer) -> int:
    """Bytes of the rows live transitions really use, plus all per-transition arrays."""
    total = buffer.rewards.nbytes + buffer.dones.nbytes + buffer.timeouts.nbytes
    for pool in buffer.pools:
        total += pool.used * pool.row_nbytes + pool.start.nbytes + pool.count.nbytes
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--transitions", type=int, default=20_000, help="buffer size (ring rows)")
    parser.add_argument("--episode-length", type=int, default=100, help="steps per episode (1: no sharing)")
    parser.add_argument("--skip-threads", action="store_true", help="skip the 1 vs 2 threads learner timing")
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = PaperScaleGraphEnv()
    size = args.transitions
    dict_buffer = DictReplayBuffer(size, env.observation_space, env.action_space, device="cpu")
    dict_bytes = sum(a.nbytes for a in dict_buffer.observations.values()) * 2
    dict_bytes += dict_buffer.actions.nbytes + dict_buffer.rewards.nbytes + dict_buffer.dones.nbytes
    dict_bytes += dict_buffer.timeouts.nbytes
    del dict_buffer  # its arrays do not depend on the contents: no need to fill it

    graph_buffer = GraphReplayBuffer(size, env.observation_space, env.action_space, device="cpu")
    fill([graph_buffer], env, size, episode_length=args.episode_length)
    filled_alloc, filled_live = graph_buffer.nbytes, live_bytes(graph_buffer)
    fill([graph_buffer], env, size, episode_length=args.episode_length)  # the ring wraps: steady state
    wrapped_alloc = graph_buffer.nbytes

    per_dict = dict_bytes / size
    rows = [["DictReplayBuffer (padded)", f"{per_dict:,.0f}", "1.0", f"{per_dict * 1e6 / 1e9:.1f}"]]
    for name, total in (
        ("GraphReplayBuffer, live rows", filled_live),
        ("GraphReplayBuffer, allocated after filling", filled_alloc),
        ("GraphReplayBuffer, allocated after wrap-around", wrapped_alloc),
    ):
        per = total / size
        rows.append([name, f"{per:,.0f}", f"{per_dict / per:.1f}", f"{per * 1e6 / 1e9:.2f}"])
    print(
        f"## Replay memory ({size:,} transitions, ~20 vertices / ~60 edges, max 64 / 1024, "
        f"episodes of {args.episode_length})\n"
    )
    print(machine_line() + "\n")
    print(
        markdown_table(["buffer", "bytes/transition", "x smaller than Dict", "GB for 1M transitions"], rows)
    )
    if not args.skip_threads:
        print("\n" + threads_table())


if __name__ == "__main__":
    main()
