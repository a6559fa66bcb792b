"""Does the cheap "tuning" preset rank reward weights like the full environment? Rank correlation.

Draws ``--configs`` sets of the five reward weights the way ``sb3-graph tune`` samples them
(log-uniform within ``--weight-spread`` of Table I, sampler seed ``--seed``), and puts each set
through two trials of ``sb3_graph.tuning.runner.run_trial`` with the same training seed: one on the
reduced "tuning" preset (``envs.evaluation.tuning.TUNING_PRESET``), one on the full environment of
``zoo_configs/td3.yml``, each trained for ``--timesteps`` steps and scored with the task metrics of
``envs.evaluation.tuning.evaluate_model`` on the same validation scenarios. Prints both flow rates, collision
rates and wall times per set, and Spearman's rho and Kendall's tau between the two rankings of
the flow rate (a rho near 1: the cheap evaluation ranks weights like the full one).

Budget: ``2 * --configs`` trainings of ``--timesteps`` steps. At the default (8 sets, 20,000
steps) that is hours on a 2-core machine; ``--configs 3 --timesteps 600`` is a smoke run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import optuna
import torch
from graph_bench_utils import machine_line, markdown_table
from scipy.stats import kendalltau, spearmanr

import envs  # noqa: F401 - registers the environments
from envs.evaluation.tuning import evaluate_model, tuning_env_kwargs
from sb3_graph.files.experiment_files import check_entry, merge_env_kwargs, read_experiment
from sb3_graph.tuning.objectives import make_objective
from sb3_graph.tuning.runner import TrialSettings, run_trial

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "CoopIntersection4Way-v0"
TABLE_I = {"velocity": 0.03, "action": 0.01, "idle": 0.01, "proximity": 0.2, "collision": 1.0}


def scores(entry: dict, params: list[dict], args: argparse.Namespace) -> list[dict]:
    """Flow rate, collision rate and wall time of one trial per parameter set, on ``entry``'s env."""
    settings = TrialSettings(
        env_id=ENV_ID,
        entry=entry,
        timesteps=args.timesteps,
        objective=make_objective("flow", max_collision_rate=1.0),
        evaluator=evaluate_model,
        weight_defaults=dict(TABLE_I),
        weight_spread=args.weight_spread,
        evaluations=1,
        eval_episodes=args.eval_episodes,
        seed=args.train_seed,
    )
    study = optuna.create_study(direction="maximize")
    results = []
    for index, param in enumerate(params):
        study.enqueue_trial(param)
        tic = time.perf_counter()
        study.optimize(lambda trial: run_trial(trial, settings), n_trials=1)
        trial = study.trials[-1]
        # every set trains with the same seed on both environments: the weights are the only change
        assert trial.number == index
        results.append(
            {
                "flow": trial.user_attrs.get("flow_rate", float("nan")),
                "collision": trial.user_attrs.get("collision_rate", float("nan")),
                "seconds": time.perf_counter() - tic,
            }
        )
        print(f"  set {index}: {results[-1]}", flush=True)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=int, default=8, help="weight sets")
    parser.add_argument("--timesteps", type=int, default=20_000, help="training steps of each trial")
    parser.add_argument("--eval-episodes", type=int, default=5, help="validation scenarios")
    parser.add_argument("--weight-spread", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0, help="seed of the weight sets")
    parser.add_argument("--train-seed", type=int, default=0, help="base training seed (set k: seed + k, both envs)")
    parser.add_argument("--learning-starts", type=int, default=None, help="override the entry's (smoke runs)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    full = check_entry(read_experiment(ROOT / "zoo_configs" / "td3.yml", ENV_ID))
    if args.learning_starts is not None:
        full["learning_starts"] = args.learning_starts
    cheap = {**full, "env_kwargs": merge_env_kwargs(full.get("env_kwargs") or {}, tuning_env_kwargs())}
    sampler = optuna.samplers.RandomSampler(seed=args.seed)
    space = {
        f"weight.{term}": optuna.distributions.FloatDistribution(
            w / args.weight_spread, w * args.weight_spread, log=True
        )
        for term, w in TABLE_I.items()
    }
    draw = optuna.create_study(sampler=sampler)
    params = [draw.ask(space).params for _ in range(args.configs)]
    print("tuning preset:", flush=True)
    cheap_scores = scores(cheap, params, args)
    print("full environment:", flush=True)
    full_scores = scores(full, params, args)
    rows = [
        [str(i), f"{c['flow']:.3f}", f"{f['flow']:.3f}", f"{c['collision']:.3f}", f"{f['collision']:.3f}",
         f"{c['seconds']:.0f}", f"{f['seconds']:.0f}"]
        for i, (c, f) in enumerate(zip(cheap_scores, full_scores))
    ]  # fmt: skip
    print(markdown_table(["set", "flow (preset)", "flow (full)", "coll. (preset)", "coll. (full)", "s (preset)",
                          "s (full)"], rows))  # fmt: skip
    rho = spearmanr([c["flow"] for c in cheap_scores], [f["flow"] for f in full_scores])[0]
    tau = kendalltau([c["flow"] for c in cheap_scores], [f["flow"] for f in full_scores])[0]
    print(f"flow rate ranking, preset vs full: Spearman rho {rho:.3f}, Kendall tau {tau:.3f} ({args.configs} sets)")
    print(f"{args.timesteps} steps per trial, {args.eval_episodes} validation scenarios")
    print(machine_line())


if __name__ == "__main__":
    main()
