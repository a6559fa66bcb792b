"""Batch building: 256 graphs into one disjoint graph, ours vs ``torch_geometric.data.Batch.from_data_list``.

Three ways to get the batch the GNN consumes, on the same 256 paper-scale graphs (~20 vertices,
~60 edges, ``max_nodes=64``, ``max_edges=1024``):

- ``padded_to_batch`` on SB3's padded float tensors (what ``predict`` and ``DictReplayBuffer`` give),
- ``GraphReplayBuffer`` sampling (ragged storage -> batch, includes the sampling itself),
- PyG's ``Batch.from_data_list`` on ready-made ``Data`` objects (the reference).

Target: >= 5x faster than PyG. Also times the graph learner with 1 and 2 torch threads.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from graph_bench_utils import PaperScaleGraphEnv, fill, machine_line, markdown_table, rate, threads_table
from stable_baselines3.common.utils import obs_as_tensor
from torch_geometric.data import Batch, Data

from sb3_graph import GraphReplayBuffer
from sb3_graph.common.batching import padded_to_batch

BATCH = 256


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=1.0, help="minimum seconds per timing run")
    parser.add_argument("--skip-threads", action="store_true", help="skip the 1 vs 2 threads learner timing")
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = PaperScaleGraphEnv()
    env.reset(seed=0)
    graphs = [env.graph() for _ in range(BATCH)]
    space = env.observation_space

    padded = obs_as_tensor({k: np.stack([g[k] for g in graphs]) for k in graphs[0]}, "cpu")
    padded = {k: v.float() for k, v in padded.items()}  # as SB3's preprocessing hands it over
    data_list = []
    for g in graphs:
        x, edge_index, edge_type = space.decode(g)
        data_list.append(
            Data(
                x=torch.as_tensor(x),
                edge_index=torch.as_tensor(edge_index),
                edge_type=torch.as_tensor(edge_type),
            )
        )
    buffer = GraphReplayBuffer(BATCH, space, env.action_space, device="cpu")
    fill([buffer], env, BATCH)

    ours = padded_to_batch(padded)
    reference = Batch.from_data_list(data_list)
    assert torch.equal(ours.edge_index, reference.edge_index) and torch.equal(ours.x, reference.x)

    pyg = rate(lambda: Batch.from_data_list(data_list), args.seconds)
    results = [
        ("padded_to_batch (SB3 padded float tensors)", rate(lambda: padded_to_batch(padded), args.seconds)),
        (
            "GraphReplayBuffer.sample (ragged storage, incl. sampling)",
            rate(lambda: buffer.sample(BATCH), args.seconds),
        ),
        ("torch_geometric Batch.from_data_list (reference)", pyg),
    ]
    rows = [[name, f"{1e3 / value:.2f}", f"{value / pyg:.1f}"] for name, value in results]
    print(f"## Batch building ({BATCH} graphs, ~20 vertices / ~60 edges, 1 torch thread)\n")
    print(machine_line() + "\n")
    print(markdown_table(["method", "ms per batch", "x faster than PyG"], rows))
    if not args.skip_threads:
        print("\n" + threads_table())


if __name__ == "__main__":
    main()
