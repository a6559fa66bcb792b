"""Record (or replay) reference trajectories of the intersection environment.

The fixture ``tests/data/simulation_regression.npz`` holds, for a few fixed cases (layouts,
traffic, planners; some collide), per policy step: the vehicle ids, centre positions and speeds,
the observation (vertex features and edges), the reward terms and every metric event of
``info`` (entered, crossed, removed, stopped, governed, collisions, collided, waiting).
``tests/test_simulation_regression.py`` replays the cases with the code under test and compares.

The committed fixture was recorded before the simulation was vectorized further (issue #16), so
the test proves that the faster code drives the same trajectories.

Run: ``python scripts/record_regression.py [--out tests/data/simulation_regression.npz]``, or with
``--check`` to print how far the code here is from the fixture.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner
from envs.planners.adversarial import FullThrottle, RandomAccel
from envs.simulation.rewards import PAPER_TERMS
from envs.simulation.traffic import generate_scenario

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "simulation_regression.npz"
# name -> (env id, planner, traffic: scenario seed or None for training traffic, steps, config)
CASES: dict[str, tuple[str, str, int | None, int, dict]] = {
    "4way_fifo": ("CoopIntersection4Way-v0", "fifo", 3, 120, {}),
    "4way_full_throttle": ("CoopIntersection4Way-v0", "full_throttle", 4, 100, {}),
    "3way_pr": ("CoopIntersection3Way-v0", "pr", 5, 100, {}),
    "inD_random": ("CoopIntersectionInD-v0", "random", 6, 100, {}),
    "inD_aim": ("CoopIntersectionInD-v0", "aim", 7, 80, {}),
    "4way_training_random": ("CoopIntersection4Way-v0", "random", None, 100, {"spawn_probability": 0.1}),
}
EVENTS = ("entered", "crossed", "removed", "stopped", "governed", "collided")


def _planner(name: str):
    if name == "full_throttle":
        return FullThrottle()
    if name == "random":
        return RandomAccel(seed=11)
    return make_planner(name)


def run_case(name: str) -> dict[str, np.ndarray]:
    """Run one case; return its per-step records as flat arrays with per-step counts.

    :param name: a key of :data:`CASES`
    :return: arrays named ``<field>`` (concatenated over steps) and ``<field>_count`` (per step)
    """
    env_id, planner_name, scenario_seed, steps, config = CASES[name]
    # The paper's reward and dropped spawns: the configuration the recording was made with.
    env = gym.make(env_id, config={"collision_handling": "remove", "reward": "paper", "spawn_queue": 0, **config})
    base = env.unwrapped
    planner = _planner(planner_name)
    options = None
    if scenario_seed is not None:
        options = {"scenario": generate_scenario(base.config["layout"], steps * 0.2, scenario_seed, (0.3, 0.5))}
    _, info = env.reset(seed=scenario_seed or 0, options=options)
    planner.reset(0)
    rec: dict[str, list[np.ndarray]] = {}

    def put(key: str, value: np.ndarray) -> None:
        rec.setdefault(key, []).append(np.asarray(value))

    for _ in range(steps):
        scene = base.scene()
        acc = np.asarray(planner.act(scene), float)
        obs, reward, _, _, info = env.step(base.accelerations_to_action(acc))
        scene = base.scene()
        put("vehicle_id", scene.vehicle_id)
        put("position", scene.position)
        put("speed", scene.speed)
        x, edge_index, edge_type = base.observation_space.decode(obs)
        put("x", x)
        put("edge_index", edge_index.T)
        put("edge_type", edge_type)
        put("reward", np.array([reward, *(info["reward_terms"][k] for k in PAPER_TERMS)]))
        for event in EVENTS:
            put(event, info[event])
        put("collisions", info["collisions"].reshape(-1, 2))
        put("waiting", np.array([info["waiting"]]))
    out: dict[str, np.ndarray] = {}
    for key, values in rec.items():
        out[key] = np.concatenate(values)
        out[f"{key}_count"] = np.array([len(v) for v in values], np.int32)
    return out


def _compact(key: str, value: np.ndarray) -> np.ndarray:
    # Integers fit in int32 (ids, rows, counts); floats stay float64 (x is float32 already).
    return value.astype(np.int32) if np.issubdtype(value.dtype, np.integer) else value


def record(out: Path = DEFAULT_OUT) -> Path:
    """Run every case and write the fixture.

    :param out: the ``.npz`` to write
    :return: the path written
    """
    warnings.filterwarnings("ignore")
    arrays = {}
    for name in CASES:
        for key, value in run_case(name).items():
            arrays[f"{name}/{key}"] = _compact(key, value)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    return out


def check(fixture: Path = DEFAULT_OUT) -> None:
    """Replay every case with the code here and print the largest differences from the fixture.

    :param fixture: a recorded ``.npz``
    """
    warnings.filterwarnings("ignore")
    with np.load(fixture) as data:
        for name in CASES:
            got = run_case(name)
            diff = {
                key: np.abs(got[key] - data[f"{name}/{key}"]).max(initial=0.0) for key in ("position", "speed", "x")
            }
            same = all(np.array_equal(got[key], data[f"{name}/{key}"]) for key in ("vehicle_id", *EVENTS))
            print(f"{name}: largest |difference| " + ", ".join(f"{k} {v:.3g}" for k, v in diff.items())
                  + f"; ids and events {'identical' if same else 'DIFFER'}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="fixture to write")
    parser.add_argument("--check", action="store_true", help="compare with the fixture instead of writing it")
    args = parser.parse_args(argv)
    if args.check:
        check(args.out)
        return 0
    path = record(args.out)
    with np.load(path) as data:
        for name in CASES:
            counts = data[f"{name}/vehicle_id_count"]
            collisions = int(data[f"{name}/collisions_count"].sum())
            print(f"{name}: {counts.size} steps, {counts.sum()} vehicle-steps, max {counts.max()} vehicles, "
                  f"{collisions} collisions, {int(data[f'{name}/governed_count'].sum())} governed")  # fmt: skip
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
