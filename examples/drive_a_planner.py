"""Drive a planner yourself: the evaluation harness's loop (``envs.evaluation.harness.run_episode``) by hand.

The environment shows a scene (every vehicle as arrays, ``envs.simulation.scene.Scene``), the planner answers
one acceleration per vehicle, and the environment turns them into its action::

    python examples/drive_a_planner.py --planner aim --seed 3 --duration 30

Any planner that ``--planner`` of ``sb3-graph evaluate`` takes works ("pr", "fifo", "aim", "signal", a policy file,
"+shield" after any of them), and so does your own class with ``reset(seed)`` and ``act(scene)``.
To watch the same run: ``sb3-graph record --planner aim --seed 3 --duration 30 --out aim.gif``.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner
from envs.simulation.traffic import generate_scenario


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planner", default="fifo")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=30.0)
    args = parser.parse_args()

    # the loop, as the harness runs it (the harness also logs every vehicle for the metrics)
    env = gym.make("CoopIntersection4Way-v0", config={"collision_handling": "remove"})
    planner = make_planner(args.planner)
    scenario = generate_scenario("4way", args.duration, args.seed)  # every vehicle's appearance, route, speed
    _, info = env.reset(seed=args.seed, options={"scenario": scenario})
    record = info["record"]  # what the step did, typed (envs.simulation.step_record.StepRecord)
    planner.reset(args.seed)
    crossed = collided = 0
    while record.time < args.duration - 1e-9:
        scene = env.unwrapped.scene()
        acc = np.asarray(planner.act(scene), dtype=float)  # one acceleration per vehicle [m/s^2]
        _, _, terminated, truncated, info = env.step(env.unwrapped.accelerations_to_action(acc))
        record = info["record"]
        crossed, collided = crossed + len(record.crossed), collided + len(record.collided)
        if terminated or truncated:
            break
    print(f"{args.planner}: {crossed} vehicles crossed, {collided} collided in {record.time:.1f} s")


if __name__ == "__main__":
    main()
