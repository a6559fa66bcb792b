"""What a planner sees: a snapshot of every vehicle in the scene as arrays, one row per vehicle.

Row ``i`` of every array, vertex ``i`` of the graph observation and action slot ``i`` are the
same vehicle. The snapshot is built by the simulation once per policy step; each planner is handed
its own :meth:`Scene.copy`, so that what it does to the arrays reaches nothing else.

What happened during a step (entries, crossings, stops, collisions) is not part of the scene: the
environment reports it in a :class:`envs.simulation.step_record.StepRecord` (and in the step ``info``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

# A vehicle whose speed falls below this has stopped (paper, "Synthetic Simulation").
STOP_SPEED = 0.3

MANEUVERS = ("left", "straight", "right")
LEFT, STRAIGHT, RIGHT = range(3)
MINOR, MAJOR = 0, 1
PRIORITY_NAMES = ("minor", "major")


@dataclass(frozen=True)
class Scene:
    """All vehicles at one instant.

    :param time: simulated time [s]
    :param dt: policy period [s]: how long the planner's accelerations are applied
    :param vehicle_id: ``(n,)`` int64 unique id of each vehicle in this episode
    :param route: ``(n,)`` int64 index into ``route_names``
    :param s: ``(n,)`` path coordinate of the paper: 0 where the path leaves the intersection
        area, ``-s_ref`` where it enters; lengths inside the intersection are scaled to ``s_ref``
    :param position: ``(n, 2)`` centre position [m]
    :param heading: ``(n,)`` heading [rad]
    :param speed: ``(n,)`` speed [m/s], never negative
    :param speed_limit: ``(n,)`` speed limit of the lane each vehicle is on [m/s]
    :param dist_to_entry: ``(n,)`` metres along the path from the vehicle's front to the stop
        line where the path enters the intersection area; negative once past it
    :param dist_to_exit: ``(n,)`` metres along the path from the vehicle's rear to where the path
        leaves the intersection area; negative once it has left
    :param leader: ``(n,)`` int64 row of the nearest vehicle ahead on the same path, -1 if none
    :param gap: ``(n,)`` bumper-to-bumper distance to the leader [m], ``inf`` if none
    :param priority: ``(n,)`` int64 ``MAJOR`` or ``MINOR``: priority of the incoming road
    :param maneuver: ``(n,)`` int64 ``LEFT``, ``STRAIGHT`` or ``RIGHT``
    :param length: ``(n,)`` vehicle length [m]
    :param route_names: name of each route, e.g. ``"south->north"``
    :param conflicts: ``(R, R)`` bool: routes whose paths cross or merge inside the intersection
    :param a_min: smallest commanded acceleration [m/s^2]
    :param a_max: largest commanded acceleration [m/s^2]
    :param width: ``(n,)`` vehicle width [m]; ``None`` means 2 m for every vehicle (added by the
        environment engineer; optional so that hand-built scenes stay short)
    :param s_ref: the common reference length of the paths inside the intersection [m]
    :param arc: ``(n,)`` arc length of the vehicle centre along its route from the route's start [m];
        ``None`` when unknown (hand-built scenes)
    :param layout: the intersection (:class:`envs.simulation.layouts.Layout`: route geometry, speed-limit
        profiles, conflict zones); ``None`` when unknown (hand-built scenes)
    :param human: ``(n,)`` bool: human-driven vehicles, which follow the static priority rules and
        ignore a planner's command; ``None`` means none (hand-built scenes)
    :param substeps: simulation sub-steps per policy period (``simulation_frequency / policy_frequency``), so
        that whoever predicts the scene (the shield) integrates as the plant does; ``None`` when unknown
        (hand-built and wire scenes: the predictor's own setting)
    :param arc_std: ``(n,)`` standard deviation of each perceived arc (and so of ``s``, the distances, the gaps)
        [m] under the environment's fault model (:mod:`envs.simulation.perception`); ``None``: exact
    :param speed_std: ``(n,)`` standard deviation of each perceived speed [m/s]; ``None``: exact
    :param age: ``(n,)`` age of the last message of each vehicle that the perceived state rests on [s] (the latency,
        plus the time its state has been held while messages were lost); ``None``: exact and current
    :param acceleration: ``(n,)`` the acceleration each vehicle realises at the scene's estimate (its commands through
        the actuation latency and lag of the fault model, as the planner side replays them) [m/s^2]; ``None``: each
        command is realised at once
    :param command: ``(n,)`` the last command each vehicle was sent, still in flight for the fault model's latency
        (it holds until the next one applies) [m/s^2]; ``None`` where ``acceleration`` is (no latency or lag)
    :param human_intent: ``(n,)`` int8: what a shield has seen each human driver do against the human model
        (:meth:`envs.planners.shield.Shield.act` sets it in the scene it hands its planner): ``1`` it went where the
        model yields (it goes, whatever the model says), ``-1`` it has stood where the model goes (it waits), ``0``
        the model's call; ``None``: the model's call for every driver (:func:`envs.planners.human.human_commands`)
    """

    time: float
    dt: float
    vehicle_id: np.ndarray
    route: np.ndarray
    s: np.ndarray
    position: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    speed_limit: np.ndarray
    dist_to_entry: np.ndarray
    dist_to_exit: np.ndarray
    leader: np.ndarray
    gap: np.ndarray
    priority: np.ndarray
    maneuver: np.ndarray
    length: np.ndarray
    route_names: tuple[str, ...]
    conflicts: np.ndarray
    a_min: float = -5.0
    a_max: float = 5.0
    width: np.ndarray | None = None
    s_ref: float = 25.0
    arc: np.ndarray | None = None
    layout: Any = None
    human: np.ndarray | None = None
    substeps: int | None = None
    arc_std: np.ndarray | None = None
    speed_std: np.ndarray | None = None
    age: np.ndarray | None = None
    acceleration: np.ndarray | None = None
    command: np.ndarray | None = None
    human_intent: np.ndarray | None = None

    @property
    def num_vehicles(self) -> int:
        return int(self.vehicle_id.shape[0])

    @property
    def humans(self) -> np.ndarray:
        """``(n,)`` bool: human-driven vehicles (all ``False`` when the scene does not say)."""
        return np.zeros(self.num_vehicles, bool) if self.human is None else np.asarray(self.human, bool)

    @property
    def approaching(self) -> np.ndarray:
        """``(n,)`` bool: the vehicle has not yet left the intersection area."""
        return self.dist_to_exit > 0

    def copy(self) -> Scene:
        """A copy whose arrays are the copy's own (the layout is shared: it is read-only).

        The harness hands each planner such a copy, so that what a planner does to the scene it is
        given reaches neither the shield, nor the metrics, nor the simulation.
        """
        own = {f.name: getattr(self, f.name) for f in fields(self)}
        return replace(self, **{k: v.copy() for k, v in own.items() if isinstance(v, np.ndarray)})
