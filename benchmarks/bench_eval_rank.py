"""Does a study's cheap validation rank trained planners like the full evaluation? Rank correlation.

A trial of ``sb3-graph tune`` is scored by ``envs.evaluation.tuning.evaluate_model``: a few short validation
scenarios (``--episodes``, default 6, 40 s each, seed ``--eval-seed`` 500) on the reduced "tuning"
preset. The results in docs/results.md come from ``sb3-graph evaluate``: 100 s scenarios of the full
environment, every scheduled vehicle counted. This script scores the same trained models both ways
and prints Spearman's rho and Kendall's tau between the two rankings of the flow rate:

    python benchmarks/bench_eval_rank.py --report reports/cmp_table1 --report reports/cmp_tuned \\
        --model table1=runs/cmp/table1 --model tuned=runs/cmp/tuned

``--model LABEL=FOLDER`` takes ``FOLDER/seed_*/final_model.zip`` (read with SB3's full load: your own
runs only); ``--report`` folders are ``sb3-graph evaluate`` reports in which the planner
``RL:seed_<k>`` (unshielded) of each LABEL's report is that model. Reports are matched to labels by
order. Budget: one cheap validation per model, seconds each.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch
from graph_bench_utils import machine_line, markdown_table
from scipy.stats import kendalltau, spearmanr

import envs  # noqa: F401 - registers the environments
from envs.evaluation.tuning import evaluate_model, tuning_env_kwargs
from sb3_graph import TD3

ENV_ID = "CoopIntersection4Way-v0"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, help="LABEL=FOLDER with seed_*/final_model.zip")
    parser.add_argument("--report", action="append", required=True, help="sb3-graph evaluate report, one per --model")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--eval-seed", type=int, default=500)
    args = parser.parse_args()
    if len(args.model) != len(args.report):
        parser.error("give one --report per --model")
    torch.set_num_threads(1)
    rows = []
    for spec, report in zip(args.model, args.report):
        label, folder = spec.split("=", 1)
        full = pd.read_csv(Path(report) / "metrics.csv").groupby("planner")["flow_rate"].mean()
        for path in sorted(Path(folder).glob("seed_*/final_model.zip")):
            model = TD3.load(path, device="cpu")
            cheap = evaluate_model(model, ENV_ID, tuning_env_kwargs(), episodes=args.episodes, seed=args.eval_seed)
            name = f"RL:{path.parent.name}"
            rows.append(
                {
                    "model": f"{label}/{path.parent.name}",
                    "cheap flow": round(cheap["flow_rate"], 3),
                    "cheap collisions": round(cheap["collision_rate"], 3),
                    "full flow": round(float(full[name]), 3),
                }
            )
    table = pd.DataFrame(rows)
    print(machine_line())
    print(markdown_table(list(table.columns), [[str(v) for v in row] for row in table.values.tolist()]))
    rho = spearmanr(table["cheap flow"], table["full flow"]).statistic
    tau = kendalltau(table["cheap flow"], table["full flow"]).statistic
    print(f"\n{len(table)} models: Spearman rho {rho:.2f}, Kendall tau {tau:.2f}")


if __name__ == "__main__":
    main()
