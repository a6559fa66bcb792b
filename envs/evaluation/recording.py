"""One episode run for watching: the harness's loop with a frame kept per policy step.

``sb3-graph record`` runs each planner here (:func:`record_episode`) and hands the episodes to
:func:`envs.simulation.rendering.write_animation`, which draws them as GIF, MP4 or HTML.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from envs.evaluation.harness import run_episode
from envs.simulation.rendering import Episode, EpisodeRecorder


def record_episode(
    env,
    planner,
    name: str,
    scenario: Any,
    duration: float,
    seed: int | None = None,
    tick: Callable[[], Any] | None = None,
) -> Episode:
    """Run one planner through one scenario with the harness's loop, keeping a frame per policy step.

    :param env: the harness's environment (:func:`envs.evaluation.harness.evaluation_env_kwargs`)
    :param planner: a :class:`envs.planners.Planner`
    :param name: its report name
    :param scenario: a :class:`envs.simulation.traffic.Scenario` (or a file)
    :param duration: simulated seconds
    :param seed: seed of the environment's reset and of the planner (the harness's ``seed + index``)
    :param tick: called once per policy step (progress)
    :return: the episode, its facts with the run's ``crossed`` and ``collided`` vehicles
    """
    recorder = EpisodeRecorder(planner, tick)
    vehicles, facts = run_episode(env, planner, scenario, duration, seed=seed, on_step=recorder)
    facts = {**facts, "crossed": int(vehicles["crossed"].notna().sum()), "collided": int(vehicles["collided"].sum())}
    return Episode(name, env.unwrapped.layout, recorder.frames, facts)
