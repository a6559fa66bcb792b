"""First in, first out per group of conflicting paths (FIFO), the paper's AIM-like baseline.

Vehicles are ordered by their distance to the intersection (closest first). A vehicle may enter
when no earlier vehicle on a *conflicting* path holds or is about to take the intersection
(see :func:`envs.planners.idm.blocked_by_rank`); vehicles on paths that do not conflict go at
the same time, so the order is strict only within groups of conflicting paths, not over the
whole intersection. Otherwise it waits at the stop point (its line). Car following is IDM.

The times a vehicle arrives at and clears the intersection come from the vehicle model
(:func:`envs.planners.vehicle_model.model_crossing_times`: lane limits, the governor's braking,
the acceleration of the crossing), with small margins tuned under a zero-collision constraint
(``docs/baselines.md``) instead of fixed rules of thumb.

Human drivers (mixed traffic) ignore the order: one that the priority rules let go comes first, with
the shield's predicted window (:func:`envs.planners.human.human_window`) as its arrival and clearing;
one that they hold comes last (FIFO holds no automated vehicle for a human who yields to it).
"""

from __future__ import annotations

import numpy as np

from envs.planners.human import approach_limit, human_commands, human_window
from envs.planners.idm import DEFAULT_IDM, CrossingParams, IDMParams, blocked_by_rank
from envs.planners.vehicle_model import model_crossing_times
from envs.planners.yielding import YieldingPlanner, rank_by
from envs.simulation.scene import Scene

# Tuned with Optuna under a zero-collision constraint (docs/baselines.md): the clearing acceleration
# of IDM's crossings and the margins [s].
FIFO_CROSSING = CrossingParams(clear_accel=3.33, gap_margin=0.96, hold_margin=0.0, follow_offset=0.44, commit_dec=3.67)


class FIFOPlanner(YieldingPlanner):
    """FIFO over groups of conflicting paths, IDM car following, vehicle-model occupancy times.

    :param name: the name shown in reports
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the admission logic (default: :data:`FIFO_CROSSING`)
    :param governor_deceleration: the simulation's governor deceleration [m/s^2]
    :param human_margin: seconds added on both sides of a going human driver's predicted window
    :param human_horizon: latest clearing predicted for a going human driver at a crawl [s]
    """

    default_name = "FIFO"

    def __init__(
        self,
        name: str | None = None,
        idm: IDMParams = DEFAULT_IDM,
        crossing: CrossingParams | None = None,
        governor_deceleration: float = 3.0,
        human_margin: float = 1.0,
        human_horizon: float = 8.0,
    ) -> None:
        super().__init__(name, idm, crossing if crossing is not None else FIFO_CROSSING)
        self.governor_deceleration = governor_deceleration
        self.human_margin = human_margin
        self.human_horizon = human_horizon

    def rank(self, scene: Scene) -> np.ndarray:
        """Closest to the stop line first, ties by id."""
        return rank_by(scene.dist_to_entry, scene.vehicle_id)

    def blocked(self, scene: Scene) -> np.ndarray:
        if scene.layout is None:  # hand-built scene without geometry: the rules of thumb
            return blocked_by_rank(scene, self.rank(scene), CrossingParams())
        times = model_crossing_times(scene, self.crossing, self.governor_deceleration)
        rank = self.rank(scene)
        if scene.humans.any():
            rank, times = self._human_terms(scene, rank, times)
        return blocked_by_rank(scene, rank, self.crossing, times=times)

    def _human_terms(
        self, scene: Scene, rank: np.ndarray, times: tuple[np.ndarray, ...]
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Human drivers ignore the order: one that the priority rules let go comes first, with the
        window of the shield's rule (:func:`envs.planners.human.human_window`) as its arrival and
        clearing; one that they hold comes last (it yields: FIFO holds no one for it)."""
        human = scene.humans
        going = human_commands(scene)[1]
        n = scene.num_vehicles
        rank = np.where(going, rank - n, np.where(human, rank + n, rank))
        arrival, clearing, inside, committed = times
        rows = np.flatnonzero(going)  # only the going humans' windows are read
        entry, leave = scene.dist_to_entry[rows], scene.dist_to_exit[rows]
        start, until = human_window(
            entry,
            leave,
            scene.speed[rows],
            approach_limit(scene, rows, entry),
            self.human_margin,
            self.human_horizon,
        )
        arrival, clearing = arrival.copy(), clearing.copy()
        arrival[rows] = start
        clearing[rows[leave > 0]] = until[leave > 0]  # one that has left keeps its clearing
        return rank, (arrival, clearing, inside, committed)
