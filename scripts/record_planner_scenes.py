"""Record scenes and planner answers for the regression test of the fast shield and AIM.

Runs a few planners through short generated evaluation scenarios in the harness's environment
and stores, per policy step, the scene's arrays, the wrapped planner's proposal and the answer
(``tests/data/planner_scenes.npz``). ``tests/test_planner_regression.py`` rebuilds the scenes and
checks that today's planners answer the same.

Regenerate (only when a behaviour change is deliberate)::

    PYTHONPATH=$PWD python scripts/record_planner_scenes.py
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs
from envs.planners import make_planner
from envs.planners.adversarial import FullThrottle
from envs.planners.base import Planner
from envs.planners.shield import Shield
from envs.simulation.traffic import generate_scenario

# Scene arrays stored per vehicle (everything a Scene holds besides the layout's tables).
FIELDS = (
    "vehicle_id", "route", "s", "position", "heading", "speed", "speed_limit", "dist_to_entry",
    "dist_to_exit", "leader", "gap", "priority", "maneuver", "length", "width", "arc",
)  # fmt: skip
# (run name, env id, planner word or class, scenario seed, seconds)
RUNS = (
    ("aim", "CoopIntersection4Way-v0", "aim", 11, 30.0),
    ("signal", "CoopIntersection4Way-v0", "signal", 12, 30.0),
    ("pr+shield", "CoopIntersection4Way-v0", "pr+shield", 13, 30.0),
    ("aim+shield", "CoopIntersection4Way-v0", "aim+shield", 14, 30.0),
    ("fullthrottle+shield", "CoopIntersection4Way-v0", "FullThrottle+shield", 15, 30.0),
    ("fullthrottle+shield_3way", "CoopIntersection3Way-v0", "FullThrottle+shield", 16, 20.0),
)


class _Recorder(Planner):
    """Passes a planner's answer through and keeps it (the shield's proposal)."""

    def __init__(self, planner: Planner) -> None:
        super().__init__(planner.name)
        self.planner = planner
        self.last = np.zeros(0)

    def reset(self, seed: int | None = None) -> None:
        self.planner.reset(seed)

    def act(self, scene) -> np.ndarray:
        self.last = np.asarray(self.planner.act(scene), float)
        return self.last


def _planner(word: str) -> Planner:
    if word.endswith("+shield"):
        inner = word[: -len("+shield")]
        return Shield(_Recorder(FullThrottle() if inner == "FullThrottle" else make_planner(inner)))
    return make_planner(word)


def record(env_id: str, word: str, seed: int, duration: float) -> dict[str, np.ndarray]:
    """Run one planner through one generated scenario and return the flattened record."""
    env = gym.make(env_id, **evaluation_env_kwargs(None))
    base = env.unwrapped
    scenario = generate_scenario(base.layout, duration, seed)
    planner = _planner(word)
    env.reset(seed=seed, options={"scenario": scenario})
    planner.reset(seed)
    rows: dict[str, list[np.ndarray]] = {name: [] for name in FIELDS}
    counts, times, proposal, action, overridden = [], [], [], [], []
    steps = int(round(duration / base.scene().dt))
    for _ in range(steps):
        scene = base.scene()
        acc = np.asarray(planner.act(scene), float)
        for name in FIELDS:
            rows[name].append(np.asarray(getattr(scene, name)))
        counts.append(scene.num_vehicles)
        times.append(scene.time)
        action.append(acc)
        if isinstance(planner, Shield):
            proposal.append(planner.planner.last.copy())
            overridden.append(planner.last_overridden.copy())
        env.step(base.accelerations_to_action(acc))
    out = {name: np.concatenate(values) for name, values in rows.items()}
    out.update(count=np.array(counts), time=np.array(times), action=np.concatenate(action))
    for name in ("dt", "a_min", "a_max", "s_ref"):
        out[name] = np.array(getattr(scene, name))
    if overridden:
        out.update(proposal=np.concatenate(proposal), overridden=np.concatenate(overridden))
    env.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[1] / "tests" / "data" / "planner_scenes.npz"
    parser.add_argument("--out", default=str(default))
    args = parser.parse_args()
    arrays: dict[str, np.ndarray] = {}
    for name, env_id, word, seed, duration in RUNS:
        for key, value in record(env_id, word, seed, duration).items():
            arrays[f"{name}/{key}"] = value
        arrays[f"{name}/env_id"] = np.array(env_id)
        print(f"{name}: {len(arrays[f'{name}/count'])} steps, {int(arrays[f'{name}/count'].sum())} vehicle-steps")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
