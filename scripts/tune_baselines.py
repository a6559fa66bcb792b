"""Tune the free parameters of a baseline planner with Optuna, under a zero-collision constraint.

Each trial runs the planner on the same few validation scenarios (drawn like the evaluation's, but
from ``--seed``, 1000 by default, never the main job's seed 0 nor the validation seed 5000) and scores
the mean flow rate; a trial with any collision scores the flow minus the number of collided vehicles,
so it never wins.

``glide`` runs behind the shield (as it is meant to) and is scored by what its job asks, in order:
delay no worse than full throttle + shield's on the same scenarios, at its flow (Optuna constraints:
mean delay minus full throttle's at most ``--delay-slack`` seconds, mean flow at least full
throttle's minus 0.002 veh/s), then the fewest stops, then the least energy (the objective: percent of
vehicles stopped plus 0.01 per kJ per vehicle). A trial that breaks a constraint never wins over one
that keeps them.

With ``--max-stop-ratio R`` the order is the other way round: the least delay (plus 0.001 s per kJ per
vehicle) among the trials that stop at most a share ``R`` of the vehicles, at full throttle's flow.

Trial 0 is the planner's current defaults (``--enqueue`` adds more JSON starting points), so that a
study never ships anything worse on its own scenarios. ``--storage`` (an Optuna journal file) lets
several processes share one study. The best parameters are printed as JSON (ship them as the
planner's defaults, see ``docs/baselines.md``).

Usage::

    PYTHONPATH=$PWD python scripts/tune_baselines.py --planner aim --trials 24 --scenarios 3 --duration 60
    PYTHONPATH=$PWD python scripts/tune_baselines.py --planner glide --trials 16 --scenarios 6 --duration 100 \
        --storage studies/glide.journal   # the same command in a second process shares the study
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import optuna

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.evaluation.metrics import run_metrics
from envs.planners.adversarial import FullThrottle
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
            "window": (5.0, 80.0),
            "floor": (0.5, 5.0),
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
# Planners scored by delay, then stops, then energy against full throttle + shield (see the module docstring).
AGAINST_FULL_THROTTLE = {"glide"}
METRICS = {
    "flow": "flow_rate",
    "delay": "delay_mean",
    "stops": "stop_ratio_all",
    "energy": "energy_kj_per_vehicle",
    "collided": "collided",
}


def _params_of(planner):
    """The dataclass that holds a built planner's tuned parameters."""
    planner = getattr(planner, "planner", planner)  # behind the shield
    return planner.params if hasattr(planner, "params") else planner.crossing


def _run(env, planner, scenarios, duration: float, seed: int) -> dict[str, float]:
    """Mean flow, delay, stop ratio and energy of ``planner`` over ``scenarios``, and its collided vehicles."""
    rows = []
    for k, scenario in enumerate(scenarios):
        log, facts = run_episode(env, planner, scenario, duration, seed=seed + k)
        rows.append(run_metrics(log, facts["duration"]))
    out = {key: float(np.nanmean([row[col] for row in rows])) for key, col in METRICS.items()}
    out["collided"] = float(sum(int(row["collided"]) for row in rows))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planner", choices=sorted(SPACES), required=True)
    parser.add_argument("--trials", type=int, default=24)
    parser.add_argument("--scenarios", type=int, default=3)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--seed", type=int, default=1000, help="seed of the validation scenarios")
    parser.add_argument("--layout", default="4way")
    parser.add_argument("--storage", default=None, help="an Optuna journal file shared by several processes")
    parser.add_argument("--delay-slack", type=float, default=0.0, help="glide: allowed delay over full throttle [s]")
    parser.add_argument("--max-stop-ratio", type=float, default=None, help="glide: least delay under this stop ratio")
    parser.add_argument("--enqueue", action="append", default=[], help="JSON parameters of an extra first trial")
    args = parser.parse_args()
    space, build = SPACES[args.planner]
    env_id = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}
    env = gym.make(env_id[args.layout], **evaluation_env_kwargs({}))
    scenarios = [generate_scenario(args.layout, args.duration, args.seed + k) for k in range(args.scenarios)]
    scored = args.planner in AGAINST_FULL_THROTTLE
    if scored:
        reference = _run(env, Shield(FullThrottle()), scenarios, args.duration, args.seed)
        print(json.dumps({"fullthrottle+shield": reference}), flush=True)

    def objective(trial: optuna.Trial) -> float:
        planner = build({name: trial.suggest_float(name, lo, hi) for name, (lo, hi) in space.items()})
        means = _run(env, planner, scenarios, args.duration, args.seed)
        for key, value in means.items():
            trial.set_user_attr(key, value)
        if not scored:
            return means["flow"] - means["collided"]
        constraints = {
            "flow": reference["flow"] - 0.002 - means["flow"],
            "collided": means["collided"],
        }
        if args.max_stop_ratio is None:
            constraints["delay"] = means["delay"] - reference["delay"] - args.delay_slack
        else:
            constraints["stops"] = means["stops"] - args.max_stop_ratio
        for key, value in constraints.items():
            trial.set_constraint(key, value)
        trial.set_user_attr("feasible", all(value <= 0 for value in constraints.values()))
        if args.max_stop_ratio is None:
            return 100.0 * means["stops"] + 0.01 * means["energy"]
        return means["delay"] + 0.001 * means["energy"]

    tic = time.perf_counter()
    storage = None
    if args.storage:
        Path(args.storage).parent.mkdir(parents=True, exist_ok=True)
        storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(args.storage))
    sampler = optuna.samplers.TPESampler(seed=args.seed + os.getpid() % 1000 if storage else args.seed)
    study = optuna.create_study(
        study_name=f"tune-{args.planner}",
        storage=storage,
        load_if_exists=True,
        direction="minimize" if scored else "maximize",
        sampler=sampler,
    )
    if not study.trials:
        # Trial 0: the current defaults, so that the study never ships anything worse.
        defaults = {name: getattr(_params_of(build({})), name) for name in space}
        for start in [defaults, *(json.loads(text) for text in args.enqueue)]:
            study.enqueue_trial({k: float(min(max(v, space[k][0]), space[k][1])) for k, v in start.items()})
    study.optimize(objective, n_trials=args.trials)
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if scored:  # the best feasible trial (Optuna's best_trial ignores the constraints)
        feasible = [t for t in done if t.user_attrs["feasible"]]
        best = min(feasible or done, key=lambda t: t.value)
    else:
        best = study.best_trial
    print(
        json.dumps(
            {
                "planner": args.planner,
                "budget": f"{len(done)} trials x {args.scenarios} scenarios x {args.duration:g} s (seed {args.seed})",
                "best_score": best.value,
                **{key: best.user_attrs[key] for key in METRICS},
                "feasible": best.user_attrs.get("feasible", True),
                "params": {k: round(v, 3) for k, v in best.params.items()},
                "wall_s": round(time.perf_counter() - tic, 1),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
