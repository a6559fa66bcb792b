"""A planner's only influence on the world is the array it returns (DESIGN.md, "Trust boundaries")."""

import json
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from envs.evaluation.harness import Job, generate_scenarios, run_job
from envs.planners.hostile import LayoutEditor
from envs.simulation.engine import Simulation
from envs.simulation.layouts import LAYOUT_NAMES, build_layout

ROOT = Path(__file__).resolve().parents[1]
ENV = "CoopIntersection4Way-v0"


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_every_layout_array_is_read_only_down_to_its_buffer(name):
    layout = build_layout(name)
    arrays = {k: v for k, v in vars(layout).items() if isinstance(v, np.ndarray)}
    assert {"speed_limit", "xy", "heading", "conflicts", "zone_start", "exit_arc"} <= set(arrays)
    for key, value in arrays.items():
        assert not value.flags.writeable, key
        with pytest.raises(ValueError):
            value.setflags(write=True)
        if isinstance(value.base, np.ndarray):
            with pytest.raises(ValueError):
                value.base.setflags(write=True)
    for envelope in (layout.speed_envelope(3.0), layout._envelopes_squared.get(3.0, layout.speed_envelope(3.0))):
        with pytest.raises(ValueError):
            envelope[...] = 20.0
    with pytest.raises(AttributeError, match="read-only"):
        layout.speed_limit = np.full_like(layout.speed_limit, 20.0)


def test_the_attacks_are_refused_and_the_limits_stay():
    layout = build_layout("4way")
    before = layout.speed_limit.copy()
    planner = LayoutEditor()
    sim = Simulation(layout)
    sim.add(np.array([0]), np.array([5.0]), np.array([1]))
    planner.act(sim.scene())
    assert planner.refused > 0
    np.testing.assert_array_equal(layout.speed_limit, before)


def test_a_scene_copy_shares_no_array_with_the_simulation():
    sim = Simulation(build_layout("4way"))
    sim.add(np.array([0, 0]), np.array([5.0, 5.0]), np.array([1, 2]), arc=np.array([10.0, 30.0]))
    scene = sim.scene()
    copy = scene.copy()
    for f in fields(scene):
        value = getattr(scene, f.name)
        if isinstance(value, np.ndarray):
            assert not np.shares_memory(value, getattr(copy, f.name)), f.name
    position, _ = sim.pose()
    leader, _ = sim.leaders()
    assert not np.shares_memory(scene.position, position) and not np.shares_memory(scene.leader, leader)


def _same(a: dict, b: dict) -> bool:
    """Equal rows, a figure that is NaN in both (e.g. the human drivers' delay without any) included."""
    return a.keys() == b.keys() and all(a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]) for k in a)


def _run(tmp_path, spec: str, layout: str = "4way", duration: float = 20.0, seed: int = 8383):
    env_id = {"4way": ENV, "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}[layout]
    folder = tmp_path / f"scenarios_{layout}_{seed}"
    if not folder.exists():
        generate_scenarios(folder, 1, duration, seed, layout)
    path = sorted(folder.glob("*.json"))[0]
    row, vehicles = run_job(Job(spec, spec, str(path), 0, env_id, duration, seed))
    row.pop("wall_s")
    return row, vehicles


@pytest.mark.parametrize("layout", ["4way", "inD"])
def test_a_planner_that_writes_into_its_scene_and_layout_changes_no_shield_decision_and_no_metric(tmp_path, layout):
    # SceneEditor answers full throttle after overwriting every array it was handed: the shield and
    # the metrics must see exactly what they see behind an honest full-throttle planner.
    honest, honest_vehicles = _run(tmp_path, "envs.planners.adversarial:FullThrottle+shield", layout)
    editor, editor_vehicles = _run(tmp_path, "envs.planners.hostile:SceneEditor+shield", layout)
    assert honest["shield_interventions"] > 0  # the shield had work to do
    for row in (honest, editor):
        row.pop("planner")
    assert _same(editor, honest)
    assert editor_vehicles.drop(columns="planner").equals(honest_vehicles.drop(columns="planner"))
    # and without the shield: the metrics read the harness's scene, not the planner's copy
    bare, _ = _run(tmp_path, "envs.planners.adversarial:FullThrottle", layout)
    edited, _ = _run(tmp_path, "envs.planners.hostile:SceneEditor", layout)
    for row in (bare, edited):
        row.pop("planner")
    assert _same(edited, bare)


_FRESH = """
import json, sys
from envs.evaluation.harness import Job, run_job
row, vehicles = run_job(Job("pr", "pr", sys.argv[1], 0, sys.argv[2], float(sys.argv[3]), int(sys.argv[4])))
row.pop("wall_s")
print(json.dumps({"row": row, "vehicles": vehicles.to_json()}, default=str))
"""


def test_a_later_planner_is_bit_identical_to_a_fresh_process(tmp_path):
    for spec in ("envs.planners.hostile:LayoutEditor", "envs.planners.hostile:SceneEditor+shield"):
        _run(tmp_path, spec, duration=10.0)
    row, vehicles = _run(tmp_path, "pr", duration=10.0)
    path = sorted((tmp_path / "scenarios_4way_8383").glob("*.json"))[0]
    out = subprocess.run(
        [sys.executable, "-c", _FRESH, str(path), ENV, "10.0", "8383"],
        capture_output=True, text=True, check=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    fresh = json.loads(out.stdout.strip().splitlines()[-1])
    assert json.loads(json.dumps(row, default=str)) == fresh["row"]
    assert vehicles.to_json() == fresh["vehicles"]
