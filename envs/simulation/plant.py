"""The plant: whatever moves the vehicles. Our own simulation is one plant, Eclipse SUMO the second.

A plant loads a scenario's vehicles as they appear (:meth:`Plant.add`, after :meth:`Plant.spawn_free` said
there is room), steps with one acceleration per vehicle (:meth:`Plant.step`), and gives the truth: its
columns (one row per vehicle: ``route``, ``arc``, ``speed``, ``length``, ``width``, ``vehicle_id``, ``human``,
``appearance_time``), the :class:`~envs.simulation.scene.Scene` built from them (:meth:`Plant.scene`), and in
the :class:`~envs.simulation.engine.StepEvents` of each step its arrivals, removals and collisions. The
environment, the traffic and the harness talk to this interface only; :func:`make_plant` is the one place
that picks a plant, from the environment's ``plant`` config key:

- ``"builtin"``: :class:`~envs.simulation.engine.Simulation` (NumPy + numba, the default);
- ``"sumo"``: :class:`~envs.simulation.sumo_plant.SumoPlant` (Eclipse SUMO through libsumo: the ``sumo``
  extra). Its network is generated from the same :class:`~envs.simulation.layouts.Layout`
  (:mod:`envs.simulation.sumo_network`); human-driven vehicles are driven by SUMO's own driver models.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from envs.simulation.engine import PlantError, Simulation, StepEvents
from envs.simulation.layouts import Layout
from envs.simulation.scene import Scene
from envs.simulation.sumo_plant import SumoPlant

__all__ = ["PLANTS", "Plant", "PlantError", "make_plant"]

# The values of the environment's ``plant`` config key.
PLANTS = ("builtin", "sumo")


@runtime_checkable
class Plant(Protocol):
    """What a plant must do (see the module docstring). Rows are vehicles, in the order of the action slots."""

    layout: Layout
    simulation_frequency: int
    policy_frequency: int
    max_vehicles: int
    max_speed: float
    max_acceleration: float
    time: float
    route: np.ndarray
    arc: np.ndarray
    speed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    vehicle_id: np.ndarray
    appearance_time: np.ndarray
    human: np.ndarray
    drives_humans: bool  # the plant drives the human rows itself (else the environment's human model does)

    @property
    def num_vehicles(self) -> int: ...

    def reset(self) -> None:
        """Empty the scene and set the clock to 0."""

    def spawn_free(self, spawn_lane: np.ndarray, speed: np.ndarray, length: np.ndarray, min_gap: float) -> np.ndarray:
        """``(k,)`` bool: a new vehicle fits at the start of each given spawn lane."""

    def add(
        self,
        route: np.ndarray,
        speed: np.ndarray,
        vehicle_id: np.ndarray,
        length: np.ndarray | float = 5.0,
        width: np.ndarray | float = 2.0,
        arc: np.ndarray | None = None,
        human: np.ndarray | bool | None = None,
    ) -> None:
        """Append vehicles that appear now (new rows at the end)."""

    def step(self, acceleration: np.ndarray, remove_collided: bool = False) -> StepEvents:
        """Apply one acceleration per row for one policy period; finished vehicles leave the rows."""

    def scene(self) -> Scene:
        """The current snapshot, built from the columns."""

    def close(self) -> None:
        """Release what the plant holds (a SUMO simulation); the plant is unusable afterwards."""


def make_plant(layout: Layout, config: dict[str, Any], seed: int | None = None) -> Plant:
    """The plant that a validated environment configuration asks for (its ``plant`` key).

    :param layout: the intersection
    :param config: a validated environment configuration (:func:`envs.simulation.config.validate_config`)
    :param seed: the episode's seed (SUMO's drivers draw their imperfection from it; our plant draws nothing)
    :raises ValueError: for an unknown plant
    :raises ImportError: for ``"sumo"`` without the ``sumo`` extra, in one line naming it
    """
    name = config.get("plant", "builtin")
    if name not in _PLANT_CLASSES:
        raise ValueError(f"config key 'plant' must be one of {PLANTS}, got {name!r}")
    return _PLANT_CLASSES[name].from_config(layout, config, seed)


# The plant of each name (libsumo itself loads only when a SUMO plant is made).
_PLANT_CLASSES = {"builtin": Simulation, "sumo": SumoPlant}
