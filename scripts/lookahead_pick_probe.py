"""How well does the scene now predict ``lookahead``'s pick? A probe on a labelling cache.

``lookahead`` (no per-approach pass) picks one of its candidate windows for every vehicle once a second; its
labels in a ``--pretrain-cache`` of ``zoo_configs/td3_lookahead.yml`` are that pick, as one score per vehicle.
This script trains a graph-level classifier (the policies' relational trunk, mean and max pooling, a small head;
cross-entropy) on the first 80 % of the cached steps and reports its accuracy on the last 20 % (the last DAgger
round's states; of a folder of shards, ``train --label-jobs``: the last round's) against always answering the
most frequent pick::

    python scripts/lookahead_pick_probe.py runs/lookahead3.labels --steps 3000

A held-out accuracy near the majority share means that the scene now hardly tells the picks apart: a student
that answers from it regresses to their mean (docs/experiments.md, "Learning from search").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch_geometric.nn import global_max_pool, global_mean_pool

from sb3_graph.common.batching import padded_to_batch
from sb3_graph.common.networks import GraphTrunk


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cache", type=Path, help="a --pretrain-cache folder with one demonstrations-*.npz, or one "
                        "demonstrations-*/ folder of shards (train --label-jobs)")  # fmt: skip
    parser.add_argument("--steps", type=int, default=3000, help="gradient steps (default 3000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", type=Path, default=None, help="write the classifier (trunk, head, picks) here")
    args = parser.parse_args(argv)
    files = sorted(args.cache.glob("demonstrations-*.npz"))
    shards = sorted(args.cache.glob("demonstrations-*/round-*-env-*.npz"))
    if len(files) + len({f.parent for f in shards}) != 1:
        print(f"error: {args.cache} must hold one demonstrations-*.npz or one folder of shards", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    parts = [np.load(f) for f in (files or shards)]
    rounds = [int(f.name.split("-")[1]) for f in shards]
    obs = {k[4:]: np.concatenate([d[k][:-1].reshape(-1, *d[k].shape[2:]) for d in parts])
           for k in parts[0].files if k.startswith("obs/")}  # fmt: skip
    labels = np.concatenate([d["labels"].reshape(-1, d["labels"].shape[-1]) for d in parts])
    if files:  # one lockstep file: the last 20 % of its steps (the last DAgger round's states) held out
        steps, n_envs = parts[0]["labels"].shape[:2]
        late = np.arange(steps * n_envs) // n_envs >= 0.8 * steps
    else:  # shards: the last round's held out
        late = np.concatenate([np.full(d["labels"].shape[0], r == max(rounds)) for d, r in zip(parts, rounds)])
    mask = obs["node_mask"] > 0
    low = np.where(mask, labels, np.inf).min(axis=1)
    high = np.where(mask, labels, -np.inf).max(axis=1)
    uniform = high - low <= 1e-6  # one pick for every vehicle (not so where a proposal per vehicle won)
    graphs = np.flatnonzero(mask.any(axis=1) & uniform)
    mixed = int((mask.any(axis=1) & ~uniform).sum())
    first = labels[graphs, mask[graphs].argmax(axis=1)]
    picks, pick = np.unique(np.round(first, 3), return_inverse=True)
    target = np.zeros(len(labels), np.int64)
    target[graphs] = pick
    held = late[graphs]
    train, test = graphs[~held], graphs[held]
    trunk = GraphTrunk(obs["x"].shape[-1], 2, 64, (64, 64), "max", nn.ReLU, edge_dim=obs["edge_attr"].shape[-1])
    head = nn.Sequential(nn.Linear(128, 64), nn.ReLU(), nn.Linear(64, len(picks)))
    optimizer = torch.optim.Adam([*trunk.parameters(), *head.parameters()], lr=1e-3)
    y = torch.as_tensor(target)

    def logits(ids: np.ndarray) -> torch.Tensor:
        g = padded_to_batch({k: torch.as_tensor(v[ids]) for k, v in obs.items()})
        h = trunk(g.x, g.edge_index, g.edge_type, g.edge_attr)
        pooled = [global_mean_pool(h, g.batch, g.num_graphs), global_max_pool(h, g.batch, g.num_graphs)]
        return head(torch.cat(pooled, dim=1))

    rng = np.random.default_rng(args.seed)
    for _ in range(args.steps):
        ids = rng.choice(train, 128)
        loss = nn.functional.cross_entropy(logits(ids), y[ids])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        accuracy = {name: float((logits(ids).argmax(1) == y[ids]).float().mean()) for name, ids in
                    (("train", train), ("held out", test))}  # fmt: skip
    shares = np.bincount(pick, minlength=len(picks)) / len(pick)
    print(f"{len(graphs)} labelled states with one pick for all vehicles ({mixed} with a window per vehicle left "
          f"out); picks (scores) {picks.tolist()}, shares {np.round(shares, 3).tolist()}")  # fmt: skip
    if args.save is not None:
        torch.save({"trunk": trunk.state_dict(), "head": head.state_dict(), "picks": picks.tolist(),
                    "in_dim": obs["x"].shape[-1], "edge_dim": obs["edge_attr"].shape[-1]}, args.save)  # fmt: skip
    majority = np.bincount(target[test]).max() / len(test)
    print(f"accuracy: train {accuracy['train']:.3f}, held out {accuracy['held out']:.3f}; "
          f"the most frequent pick on the held-out states: {majority:.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
