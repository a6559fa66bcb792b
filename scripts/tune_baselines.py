"""Tune the free parameters of a baseline planner with Optuna, under a zero-collision constraint.

Each trial runs the planner on the same few validation scenarios (drawn like the evaluation's, but
from ``--seed``, 1000 by default, never the main job's seed 0) and scores the mean flow rate; a
trial with any collision scores the flow minus the number of collided vehicles, so it never wins.
``glide`` runs behind the shield (as it is meant to) and scores the mean flow minus 0.01 per second
of mean delay and minus 0.05 per unit of stop ratio (``SCORES``): its job is to keep full
throttle's flow while it removes stops, and flow alone would not see the stops.
The best parameters are printed as JSON (ship them as the planner's defaults, see
``docs/baselines.md``).

Usage::

    PYTHONPATH=$PWD python scripts/tune_baselines.py --planner aim --trials 24 --scenarios 3 --duration 60
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import gymnasium as gym
import numpy as np
import optuna

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.evaluation.metrics import run_metrics
from envs.planners.aim import AIMParams, AIMPlanner
from envs.planners.fifo import FIFO_CROSSING, FIFOPlanner
from envs.planners.glide import GlideParams, GlidePlanner
from envs.planners.idm import CrossingParams
from envs.planners.priority_rules import PriorityRulesPlanner
from envs.planners.shield import Shield
from envs.planners.signal import SignalParams, SignalPlanner
from envs.simulation.traffic import generate_scenario

# planner -> (search space name -> (low, high), builder from the sampled values)
SPACES = {
    "aim": (
        {
            "accel": (2.5, 4.0),
            "decel": (2.0, 3.5),
            "commit_decel": (3.5, 5.0),
            "buffer": (0.0, 0.6),
            "follow_headway": (0.0, 1.5),
            "stop_penalty": (0.0, 2.0),
        },
        lambda p: AIMPlanner(params=AIMParams(**p)),
    ),
    "fifo": (
        {
            "clear_accel": (2.0, 3.5),
            "gap_margin": (0.0, 1.0),
            "hold_margin": (0.0, 1.0),
            "follow_offset": (0.0, 1.0),
            "commit_dec": (3.5, 5.0),
        },
        lambda p: FIFOPlanner(crossing=replace(FIFO_CROSSING, **p)),
    ),
    "pr": (
        {
            "clear_accel": (1.5, 3.0),
            "gap_margin": (0.0, 1.5),
            "hold_margin": (0.0, 1.0),
            "follow_offset": (0.0, 1.0),
        },
        lambda p: PriorityRulesPlanner(crossing=CrossingParams(**p)),
    ),
    "signal": (
        {
            "min_green": (3.0, 10.0),
            "max_green": (10.0, 40.0),
            "gap": (1.0, 4.0),
            "yellow": (2.5, 4.0),
            "all_red": (0.5, 2.5),
            "detector_length": (10.0, 40.0),
        },
        lambda p: SignalPlanner(params=SignalParams(**p)),
    ),
    "glide": (
        {
            "window": (5.0, 60.0),
            "floor": (0.5, 4.0),
            "platoon_gap": (0.0, 4.0),
            "follow_headway": (0.0, 1.5),
            "decel": (1.5, 4.0),
            "commit_decel": (3.5, 5.0),
            "stop_penalty": (0.0, 3.0),
            "buffer": (0.0, 0.3),
        },
        lambda p: Shield(GlidePlanner(params=GlideParams(**p))),
    ),
}
# planner -> weights of (flow [veh/s], mean delay [s], stop ratio) in a trial's score; flow alone by default.
SCORES = {"glide": (1.0, -0.01, -0.05)}


def _params_of(planner):
    """The dataclass that holds a built planner's tuned parameters."""
    planner = getattr(planner, "planner", planner)  # behind the shield
    return planner.params if hasattr(planner, "params") else planner.crossing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planner", choices=sorted(SPACES), required=True)
    parser.add_argument("--trials", type=int, default=24)
    parser.add_argument("--scenarios", type=int, default=3)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--seed", type=int, default=1000, help="seed of the validation scenarios")
    parser.add_argument("--layout", default="4way")
    args = parser.parse_args()
    space, build = SPACES[args.planner]
    env_id = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}
    env = gym.make(env_id[args.layout], **evaluation_env_kwargs({}))
    scenarios = [generate_scenario(args.layout, args.duration, args.seed + k) for k in range(args.scenarios)]

    def objective(trial: optuna.Trial) -> float:
        planner = build({name: trial.suggest_float(name, lo, hi) for name, (lo, hi) in space.items()})
        rows = []
        for k, scenario in enumerate(scenarios):
            log, facts = run_episode(env, planner, scenario, args.duration, seed=args.seed + k)
            rows.append(run_metrics(log, facts["duration"]))
        collided = sum(int(row["collided"]) for row in rows)
        means = [float(np.mean([row[key] for row in rows])) for key in ("flow_rate", "delay_mean", "stop_ratio_all")]
        for key, value in zip(("flow", "delay", "stops"), means):
            trial.set_user_attr(key, value)
        trial.set_user_attr("collided", collided)
        return float(np.dot(SCORES.get(args.planner, (1.0, 0.0, 0.0)), means)) - collided

    tic = time.perf_counter()
    study = optuna.create_study(direction="maximize", sampler=optuna.samplers.TPESampler(seed=args.seed))
    # Trial 0: the current defaults, so that the study never ships anything worse.
    defaults = {name: getattr(_params_of(build({})), name) for name in space}
    study.enqueue_trial({k: float(min(max(v, space[k][0]), space[k][1])) for k, v in defaults.items()})
    study.optimize(objective, n_trials=args.trials)
    best = study.best_trial
    print(
        json.dumps(
            {
                "planner": args.planner,
                "budget": f"{args.trials} trials x {args.scenarios} scenarios x {args.duration:g} s (seed {args.seed})",
                "best_score": best.value,
                **{key: best.user_attrs[key] for key in ("flow", "delay", "stops")},
                "collided": best.user_attrs["collided"],
                "params": {k: round(v, 3) for k, v in best.params.items()},
                "wall_s": round(time.perf_counter() - tic, 1),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
