"""What one step of the intersection environment did, typed: :class:`StepRecord`.

The environment builds one record per ``reset`` and ``step``; the metrics (:class:`envs.evaluation.metrics.VehicleLog`),
the evaluation harness (:func:`envs.evaluation.harness.run_episode`) and the renderer read it, and nothing
else of the step. What a vehicle *is* (route, priority, maneuver, length) comes from the scenes
(:class:`envs.simulation.scene.Scene`), what *happened* to it from the records.

For gymnasium users the record also travels in the step ``info``, which keeps its keys (all ids are
``vehicle_id`` values):

- ``"record"``: the :class:`StepRecord` itself.
- ``"reward_terms"``: dict ``term -> unweighted value`` for velocity, action, idle, proximity,
  collision (and the task terms of :mod:`envs.simulation.rewards`); ``"reward_weighted"``: the same terms
  times their weights.
- ``"entered"``: ids that appeared in the scene during the step.
- ``"crossed"``: ids whose path coordinate ``s`` passed 0 (left the intersection area).
- ``"removed"``: ids that left the scene (end of their route, or collided under
  ``collision_handling="remove"``).
- ``"stopped"``: ids whose speed was below ``STOP_SPEED`` at any simulation sub-step.
- ``"governed"``: ids whose speed the speed governor lowered below what the planner commanded
  (the lane limit, or braking for a lower limit ahead).
- ``"collisions"``: ``(k, 2)`` int64 array of id pairs that collided during the step.
- ``"lost"``: ids that the plant lost on its own (SUMO refused to insert them or removed them; also in
  ``"removed"``; our simulation never loses one).
- ``"collided"``: ``(k,)`` int64 ids involved in ``"collisions"`` (distinct, sorted).
- ``"time"``: simulated time in seconds at the end of the step.
- ``"num_vehicles"``: vehicles in the scene at the end of the step.
- ``"waiting"``: scenario appearances whose time has come but whose spawn position is not free yet
  (always 0 with training traffic).
- ``"vehicles"``: dict ``id -> {"route": str, "priority": int, "maneuver": str, "time": float}``
  for the ids in ``"entered"`` (for users; the metrics read these facts from the scenes).
- ``"vertex_origin"``: for each vertex of the new observation, its slot in the previous one (``-1``
  for a vehicle that entered), so that per-vertex state such as correlated exploration noise
  follows its vehicle (``sb3_graph.callbacks.VertexNoiseCallback``); set by ``step`` only.
- ``"record"`` alone carries the step's executed motion (``moved``, ``speeds``, ``substep``: the
  speeds of every vehicle at the simulation sub-steps, after the governor and the shield), which the
  metrics read for slow vehicles, hard braking and energy (:mod:`envs.simulation.motion`).
- With ``shield=True``: ``"shield_overridden"``, ``"shield_intervention_rate"`` and
  ``"executed_action"`` (:class:`envs.simulation.env.CoopIntersectionEnv`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any

import numpy as np

_ID_FIELDS = ("entered", "crossed", "removed", "stopped", "governed", "moved", "lost")


def _no_ids() -> np.ndarray:
    return np.zeros(0, np.int64)


@dataclass(frozen=True, eq=False)
class StepRecord:
    """The events of one environment step (all ids are vehicle ids; id arrays are int64).

    :param time: simulated time at the end of the step [s]
    :param entered: ids that appeared in the scene during the step
    :param crossed: ids whose centre passed the intersection exit (``s`` passed 0)
    :param removed: ids that left the scene (end of their route, or collided under ``"remove"``)
    :param stopped: ids whose speed was below ``STOP_SPEED`` after any sub-step
    :param governed: ids whose speed the governor lowered below what the planner commanded
    :param collisions: ``(k, 2)`` id pairs whose bodies overlapped during the step
    :param num_vehicles: vehicles in the scene at the end of the step
    :param waiting: scenario appearances due but not yet placed (their spawn position is not free)
    :param reward_terms: ``term -> unweighted value``
    :param reward_weighted: the same terms times their weights
    :param moved: ids of the vehicles that the step moved (those in the scene at its start, removed ones
        included): the columns of ``speeds``
    :param speeds: ``(S + 1, len(moved))`` their executed speeds at the simulation sub-steps, row 0 the
        step's start [m/s] (after the acceleration bounds, the shield and the governor); no rows when the
        record carries no motion (``reset``, hand-built records)
    :param substep: seconds between two rows of ``speeds``
    :param lost: ids that the plant lost on its own (:attr:`envs.simulation.engine.StepEvents.lost`)
    """

    time: float = 0.0
    entered: np.ndarray = field(default_factory=_no_ids)
    crossed: np.ndarray = field(default_factory=_no_ids)
    removed: np.ndarray = field(default_factory=_no_ids)
    stopped: np.ndarray = field(default_factory=_no_ids)
    governed: np.ndarray = field(default_factory=_no_ids)
    collisions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    num_vehicles: int = 0
    waiting: int = 0
    reward_terms: Mapping[str, float] = field(default_factory=dict)
    reward_weighted: Mapping[str, float] = field(default_factory=dict)
    moved: np.ndarray = field(default_factory=_no_ids)
    speeds: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    substep: float = 0.0
    lost: np.ndarray = field(default_factory=_no_ids)

    def __post_init__(self) -> None:
        # Hand-built records may pass lists; the simulation's arrays pass through without a copy.
        for name in _ID_FIELDS:
            object.__setattr__(self, name, np.asarray(getattr(self, name), np.int64).reshape(-1))
        object.__setattr__(self, "collisions", np.asarray(self.collisions, np.int64).reshape(-1, 2))
        speeds = np.asarray(self.speeds, float)
        speeds = speeds.reshape(-1, self.moved.size) if speeds.size else np.zeros((0, self.moved.size))
        object.__setattr__(self, "speeds", speeds)

    @property
    def has_motion(self) -> bool:
        """Whether the record carries the executed sub-step speeds of its vehicles (at least one sample)."""
        return self.speeds.shape[0] >= 2 and self.substep > 0

    def __eq__(self, other: object) -> bool:
        """Field by field, arrays by value (two runs of one seeded step give equal records)."""
        if not isinstance(other, StepRecord):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    __hash__ = None  # equal by value, and mutable arrays inside

    @cached_property
    def collided(self) -> np.ndarray:
        """``(k,)`` ids involved in :attr:`collisions` (distinct, sorted)."""
        return np.unique(self.collisions) if self.collisions.size else _no_ids()

    @property
    def reward(self) -> float:
        """The step's reward: the sum of the weighted terms."""
        return float(sum(self.reward_weighted.values()))

    def info(self) -> dict[str, Any]:
        """The gymnasium step ``info`` of this record (the keys of the module docstring, but the
        environment's own ``"vehicles"`` and shield keys), the record under ``"record"``."""
        return {
            "reward_terms": self.reward_terms,
            "reward_weighted": self.reward_weighted,
            "entered": self.entered,
            "crossed": self.crossed,
            "removed": self.removed,
            "stopped": self.stopped,
            "governed": self.governed,
            "collisions": self.collisions,
            "time": self.time,
            "num_vehicles": self.num_vehicles,
            "waiting": self.waiting,
            "collided": self.collided,
            "lost": self.lost,
            "record": self,
        }


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and bool(np.array_equal(a, b))
    return bool(a == b)


def step_record(info: Mapping[str, Any]) -> StepRecord:
    """The :class:`StepRecord` that an environment's ``reset`` or ``step`` put into its ``info``.

    :param info: the step ``info``
    :raises TypeError: the environment does not report one under ``"record"``
    """
    record = info.get("record")
    if not isinstance(record, StepRecord):
        raise TypeError(
            "the environment's step info carries no envs.simulation.step_record.StepRecord under 'record' "
            f"(got {type(record).__name__}); the harness and the metrics read the step from it"
        )
    return record
