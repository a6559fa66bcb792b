"""How the world moves and what the learner sees: the intersection, its traffic and the environment.

- :mod:`~envs.simulation.layouts`: the intersections (routes, conflict zones, speed limits),
- :mod:`~envs.simulation.engine`: the vectorized vehicle simulation (:class:`Simulation`, :func:`integrate`),
- :mod:`~envs.simulation.traffic`: the training spawner and the evaluation scenario files,
- :mod:`~envs.simulation.scene`: what a planner sees (:class:`~envs.simulation.scene.Scene`),
- :mod:`~envs.simulation.graph`: the scene as the learner's graph observation,
- :mod:`~envs.simulation.rewards`: the reward terms and presets,
- :mod:`~envs.simulation.config`: validation of the environment's configuration,
- :mod:`~envs.simulation.env`: the gymnasium environments (``CoopIntersection*-v0``),
- :mod:`~envs.simulation.step_record`: what one step did, typed,
- :mod:`~envs.simulation.free_flow`: free-flow travel times (the reference of the delays),
- :mod:`~envs.simulation.rendering`: episodes drawn as GIF, MP4 or HTML.

This package re-exports the engine's names (``from envs.simulation import Simulation``); the other
modules load only when imported (the environment pulls in torch, the rendering matplotlib).
"""

from __future__ import annotations

from envs.simulation.engine import SPLIT_CLEARANCE, Simulation, StepEvents, integrate, overlapping_pairs

__all__ = ["SPLIT_CLEARANCE", "Simulation", "StepEvents", "integrate", "overlapping_pairs"]
