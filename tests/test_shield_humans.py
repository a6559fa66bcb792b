"""The shield against human drivers that do not drive as its human model: drivers of another world (SUMO's).

A driver that stands where the model lets it go waits (for another vehicle); one that goes faster than the model
commanded does not yield as the model does. The shield sees both from scene to scene and predicts them so, and its
planner sees what the shield sees (``Scene.human_intent``). The SUMO runs are the cases that collided or stood for
good before: the shield predicted SUMO's drivers with the model alone.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from envs.evaluation.harness import evaluation_env_kwargs, generate_scenarios, run_episode, run_seed
from envs.evaluation.metrics import run_metrics
from envs.planners import make_planner
from envs.planners.base import Planner
from envs.planners.human import human_commands
from envs.planners.shield import Shield
from envs.simulation.engine import Simulation
from envs.simulation.layouts import build_layout
from envs.simulation.traffic import Scenario


class _Recorder(Planner):
    """Full throttle for every vehicle; keeps the scenes it is handed."""

    def __init__(self) -> None:
        super().__init__("recorder")
        self.scenes = []

    def act(self, scene):
        self.scenes.append(scene)
        return np.full(scene.num_vehicles, scene.a_max)


def _scene(vehicles, human, layout="4way"):
    sim = Simulation(build_layout(layout))
    for k, (route, arc, speed) in enumerate(vehicles):
        sim.add(np.array([sim.layout.route_id(route)]), np.array([speed]), np.array([k]), arc=np.array([arc]),
                human=np.array([human[k]]))  # fmt: skip
    return sim.scene()


def _at(scene, time, **columns):
    return dataclasses.replace(scene, time=time, **{k: np.asarray(v, float) for k, v in columns.items()})


def test_a_human_that_stands_where_the_model_lets_it_go_waits_after_a_second():
    # A human alone at its line: the model lets it go. It stands, scene after scene.
    scene = _scene([("south->north", 70.0, 0.0)], [True])
    assert human_commands(scene)[1][0] and human_commands(scene)[0][0] > 0
    planner = _Recorder()
    shield = Shield(planner, watchdog_after=None)
    waiting = []
    for step in range(7):
        shield.act(_at(scene, 0.2 * step))
        waiting.append(bool(shield._human_view(shield._view[0])[2][0]))
    assert waiting == [False] * 5 + [True] * 2  # stood for 1 s from t = 0
    seen = planner.scenes[-1]
    assert seen.human_intent.tolist() == [-1]
    acc, going = human_commands(seen)  # the planner's model now has it waiting too
    assert not going[0] and acc[0] <= 0.0
    shield.act(_at(scene, 1.4, speed=[1.0]))  # it moves: the model's call again
    assert not shield._human_view(shield._view[0])[2][0]
    assert planner.scenes[-1].human_intent.tolist() == [0]


def test_a_human_faster_than_the_model_commanded_is_predicted_going_for_a_while():
    # A minor-road human yields to a major-road vehicle close to its zone, in the model.
    scene = _scene([("south->north", 62.0, 8.0), ("west->east", 70.0, 10.0)], [True, False])
    acc, going = human_commands(scene)
    assert not going[0]
    planner = _Recorder()
    shield = Shield(planner, watchdog_after=None, human_memory=1.0)
    shield.act(scene)
    expected = 8.0 + acc[0] * scene.dt
    faster = _at(scene, scene.time + scene.dt, speed=[expected + 1.0, 10.0], arc=[63.8, 72.0])
    assert not human_commands(faster)[1][0]  # the model still has it yield
    shield.act(faster)
    assert shield._human_view(faster)[1][0]  # the shield has it go
    assert planner.scenes[-1].human_intent.tolist() == [1, 0]
    later = faster
    for _ in range(6):  # as the model commands from then on: going until human_memory has passed
        v = max(later.speed[0] + human_commands(later)[0][0] * later.dt, 0.0)
        later = _at(later, later.time + later.dt, speed=[v, 10.0])
        shield.act(later)
    assert not shield._human_view(later)[1][0]


def test_scenes_without_humans_are_left_as_they_were():
    scene = _scene([("south->north", 62.0, 8.0), ("west->east", 70.0, 10.0)], [False, False])
    planner = _Recorder()
    Shield(planner).act(scene)
    assert planner.scenes[-1].human_intent is None


@pytest.mark.parametrize(
    ("layout", "env_id", "seed", "index", "duration", "planner"),
    [
        # A SUMO left-turner waited inside the box for an automated vehicle that the shield held for it: stuck.
        ("3way", "CoopIntersection3Way-v0", 100, 7, 60.0, "glide+shield"),
        # A SUMO driver waiting inside the box went ahead of a minor-road automated vehicle: collided.
        ("3way", "CoopIntersection3Way-v0", 100, 2, 60.0, "fullthrottle+shield"),
        # A SUMO driver that the model had yield went: a left-turner in its path, braked by everyone braking.
        ("4way", "CoopIntersection4Way-v0", 100, 0, 60.0, "fullthrottle+shield"),
        # A waiting left-turner past the start of its first zone was predicted driving on (committed) into the
        # path of a vehicle it waited for: no command passed, everyone braked, for good (the hostile table).
        ("4way", "CoopIntersection4Way-v0", 8383, 1, 80.0, "envs.planners.hostile:SceneEditor+shield"),
    ],
)
def test_the_shield_holds_against_sumos_drivers(layout, env_id, seed, index, duration, planner):
    pytest.importorskip("libsumo", reason="the sumo extra is not installed")
    with tempfile.TemporaryDirectory() as folder:
        files = generate_scenarios(Path(folder), index + 1, duration, seed, layout, human_share=0.5)
        scenario = Scenario.load(files[index])
    env = gym.make(env_id, **evaluation_env_kwargs({"config": {"plant": "sumo", "simulation_frequency": 20}}))
    shield = make_planner(planner)
    vehicles, facts = run_episode(env, shield, scenario, duration, seed=run_seed(seed, index))
    env.close()
    metrics = run_metrics(vehicles, duration)
    assert metrics["collided"] == 0
    assert not metrics["stuck"]
    assert facts["lost"] == 0
