"""TD3, SAC, TQC (and PPO) on the intersection: a short training run each, same steps, same scenarios.

Each algorithm trains with ``sb3-graph train --algo <algo> --config zoo_configs/<algo>.yml`` (the
curriculum of the config, scaled to the short run) for ``--steps`` environment steps on
``CoopIntersection4Way-v0``, seed ``--seed``. The final models then drive the same synthetic
scenarios (``--scenarios`` of ``--duration`` s, the evaluation harness's environment: collided
vehicles are removed and the run goes on), and FIFO drives them too as a reference. Prints training
wall time, flow rate (median and quartiles over scenarios), stop ratio and collision rate.

A short run says how far each algorithm gets with the same budget, not where it ends: the shipped
TD3 planner first beat FIFO after 60,000 steps.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import torch
from graph_bench_utils import machine_line, markdown_table

import envs  # noqa: F401 - registers the environments
import sb3_graph
from envs.evaluation.harness import evaluation_env_kwargs, generate_scenarios, run_episode
from envs.evaluation.metrics import run_metrics
from envs.planners import make_planner
from envs.planners.base import Planner
from envs.simulation.graph import build_observation
from envs.simulation.traffic import Scenario
from sb3_graph.cli import main as cli
from sb3_graph.commands.train import ALGORITHMS

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "CoopIntersection4Way-v0"


class ModelPlanner(Planner):
    """Any trained sb3_graph model behind the planner face (deterministic actions)."""

    def __init__(self, model, name: str) -> None:
        super().__init__(name)
        self.model = model

    def act(self, scene) -> np.ndarray:
        n = scene.num_vehicles
        if n == 0:
            return np.zeros(0)
        obs = build_observation(scene, self.model.observation_space)
        action, _ = self.model.predict(obs, deterministic=True)
        return np.clip(np.asarray(action, dtype=float)[:n] * scene.a_max, scene.a_min, scene.a_max)


def train(algo: str, steps: int, seed: int, out: Path) -> tuple[object, float]:
    code = cli(
        [
            "train", "--algo", algo, "--config", str(ROOT / "zoo_configs" / f"{algo}.yml"), "--env", ENV_ID,
            "--out", str(out), "--n-timesteps", str(steps), "--seed", str(seed), "--eval-freq", str(10 * steps),
            "--eval-episodes", "1", "--checkpoint-freq", str(10 * steps), "--no-progress",
        ]
    )  # fmt: skip
    if code != 0:
        raise SystemExit(f"training {algo} failed with exit code {code}")
    record = json.loads((out / "run.json").read_text())
    model = getattr(sb3_graph, ALGORITHMS[algo]).load(out / "final_model.zip", device="cpu")
    return model, float(record["wall_time_s"])


def evaluate(planner: Planner, scenarios: list[Path], duration: float, seed: int) -> pd.DataFrame:
    env = gym.make(ENV_ID, **evaluation_env_kwargs({}))
    rows = []
    for index, path in enumerate(scenarios):
        vehicles, facts = run_episode(env, planner, Scenario.load(path), duration, seed=seed + index)
        rows.append(run_metrics(vehicles, facts["duration"] if facts["duration"] > 0 else duration))
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--algos", nargs="+", default=["td3", "sac", "tqc"], choices=list(ALGORITHMS))
    parser.add_argument("--steps", type=int, default=20_000, help="training steps per algorithm")
    parser.add_argument("--scenarios", type=int, default=10)
    parser.add_argument("--duration", type=float, default=100.0, help="simulated seconds per scenario")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="keep the run folders here (default: a temporary folder)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out) if args.out else Path(tmp)
        scenarios = generate_scenarios(root / "scenarios", args.scenarios, args.duration, args.seed, "4way")
        planners = [(make_planner("fifo"), "", "")]
        for algo in args.algos:
            start = time.perf_counter()
            model, wall = train(algo, args.steps, args.seed, root / algo)
            print(f"{algo}: {args.steps} steps in {wall:.0f} s ({time.perf_counter() - start:.0f} s with setup)")
            planner = ModelPlanner(model, f"{ALGORITHMS[algo]} ({args.steps} steps)")
            planners.append((planner, str(args.steps), f"{wall:.0f}"))
        rows = []
        for planner, steps, wall in planners:
            metrics = evaluate(planner, scenarios, args.duration, args.seed)
            flow = metrics["flow_rate"]
            stops = metrics["stopped_all"].sum() / max(metrics["vehicles_all"].sum(), 1)
            collisions = metrics["collided"].sum() / max(metrics["vehicles"].sum(), 1)
            rows.append(
                [
                    planner.name, steps, wall,
                    f"{flow.median():.3f} ({flow.quantile(0.25):.3f}-{flow.quantile(0.75):.3f})",
                    f"{100 * stops:.1f} %", f"{100 * collisions:.2f} %", str(int(metrics["vehicles"].sum())),
                ]
            )  # fmt: skip
            print(f"evaluated {planner.name}", flush=True)
    print(f"\n## Short runs on {ENV_ID}: {args.scenarios} scenarios of {args.duration:.0f} s, seed {args.seed}\n")
    print(machine_line() + "\n")
    header = ["planner", "training steps", "training wall time [s]", "flow rate median (q1-q3) [veh/s]",
              "stopped", "collision rate", "vehicles"]  # fmt: skip
    print(markdown_table(header, rows))


if __name__ == "__main__":
    main()
