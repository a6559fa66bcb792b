"""Labelling a clone on workers: the expert's lockstep collection in this process against
:class:`~sb3_graph.common.labelling.ShardedCollector` on ``--jobs`` local processes, timed in turns.

Both label round 0 of the same VecEnv (the entry's ``n_envs`` sub-environments, seeded ``--seed``) with the
entry's expert (default ``zoo_configs/td3_lookahead.yml``: ``lookahead``, whose search is the costly part), so
they label the same states (``tests/test_labelling.py`` checks it bit for bit); the sharded collector pays for
starting its processes (spawned: they import torch and the environments) in every round. Reported: the wall
time of each, per labelled transition, and their ratio (lockstep / sharded), the median over ``--repeat`` turns.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_labelling.py --transitions 1000 --jobs 2 --repeat 2
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from graph_bench_utils import machine_line, markdown_table  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402

import envs  # noqa: E402, F401  (registers the environments)
from envs.planners.expert import PlannerExpert  # noqa: E402
from sb3_graph.common.cloning import behaviour_clone  # noqa: E402
from sb3_graph.common.labelling import LabellingJob, ShardedCollector  # noqa: E402
from sb3_graph.files.experiment_files import build_algorithm_kwargs, read_experiment  # noqa: E402
from sb3_graph.registry import ALGORITHMS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="zoo_configs/td3_lookahead.yml")
    parser.add_argument("--env", default="CoopIntersection4Way-v0")
    parser.add_argument("--transitions", type=int, default=1000, help="transitions of the round, all sub-envs")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    entry = read_experiment(args.config, args.env)
    env_kwargs = dict(entry.get("env_kwargs") or {})
    n_envs = int(entry.get("n_envs", 1))
    steps = -(-args.transitions // n_envs)

    def learner():
        env = make_vec_env(args.env, n_envs=n_envs, seed=args.seed, env_kwargs=env_kwargs)
        kwargs = build_algorithm_kwargs(entry, int(np.prod(env.action_space.shape)))
        return ALGORITHMS["td3"].load_class()("GraphPolicy", env, seed=args.seed, **kwargs)

    def lockstep() -> float:
        model = learner()
        expert = PlannerExpert(str(entry["pretrain_from"]), model.get_env())
        tic = time.perf_counter()
        behaviour_clone(model, expert, transitions=steps * n_envs, gradient_steps=0, critic_steps=0)
        return time.perf_counter() - tic

    def sharded() -> float:
        model = learner()
        job = LabellingJob(args.env, env_kwargs, str(entry["pretrain_from"]), "envs.planners.expert:make_expert",
                           ("envs",))  # fmt: skip
        tic = time.perf_counter()
        ShardedCollector(model, job, args.seed, workers=args.jobs)(0, 1.0, steps)
        return time.perf_counter() - tic

    times: dict[str, list[float]] = {"lockstep, this process": [], f"sharded, {args.jobs} processes": []}
    for k in range(args.repeat):  # in turns, the order swapped each turn
        order = [("lockstep, this process", lockstep), (f"sharded, {args.jobs} processes", sharded)]
        for name, run in order if k % 2 == 0 else order[::-1]:
            times[name].append(run())
    median = {name: float(np.median(values)) for name, values in times.items()}
    reference = median["lockstep, this process"]
    rows = [[name, f"{value:.1f}", f"{value / (steps * n_envs) * 1e3:.1f}", f"{reference / value:.2f}"]
            for name, value in median.items()]  # fmt: skip
    print(machine_line())
    print(f"command: python benchmarks/bench_labelling.py --config {args.config} --env {args.env} "
          f"--transitions {args.transitions} --jobs {args.jobs} --repeat {args.repeat} --seed {args.seed}")  # fmt: skip
    print(f"\nround 0 of {entry['pretrain_from']!r}: {steps} steps of {n_envs} sub-environments, "
          f"median of {args.repeat}\n")  # fmt: skip
    print(markdown_table(["labelling", "wall [s]", "per transition [ms]", "speed-up"], rows))


if __name__ == "__main__":
    main()
