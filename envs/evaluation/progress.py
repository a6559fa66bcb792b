"""The evaluation's progress bar, with a time left that does not extrapolate from the first runs.

A plain bar divides the runs left by the rate so far. The first runs to end are the worst sample there
is: each worker's first run of a planner also loads it (a model file, numba kernels compiled on an
installation's first run), and the runs arrive planner by planner, so that a cheap rule's runs set
the pace for a learned planner behind the shield. The main job's first estimate was 1:45:03 for a
9-minute job.

:class:`RunClock` instead weights every run by its expected cost, the simulated seconds of its
scenario times its planner's measured wall seconds per simulated second, measured on *warm* runs
only (a worker's later runs of a planner, not the one that loaded it). The time left is the cost of
the runs left divided among the workers. It stays unknown (``?``) until every planner with runs left
has a warm run: pricing one from another planner's rate is the first runs' error again. The harness
hands the runs out scenario by scenario, every planner in turn, so that every planner is measured
within the first few runs per worker and planner.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class RunClock:
    """Time left of a set of runs, from the warm runs that ended.

    :param planners: each run's planner (any hashable key), in the runs' order
    :param seconds: each run's simulated seconds (its scenario's duration, capped by the run's)
    :param workers: runs executing at once
    """

    def __init__(self, planners: Sequence[str], seconds: Sequence[float], workers: int) -> None:
        self.names, self.codes = np.unique(np.asarray([str(p) for p in planners], dtype=object), return_inverse=True)
        self.seconds = np.asarray(seconds, float)
        if len(self.codes) != len(self.seconds):
            raise ValueError(f"one planner per run: {len(self.codes)} planners for {len(self.seconds)} runs")
        self.workers = max(1, int(workers))
        self.done = np.zeros(len(self.codes), bool)
        self._wall = np.zeros(len(self.names))  # per planner: wall seconds of its warm runs
        self._simulated = np.zeros(len(self.names))  # per planner: simulated seconds of its warm runs

    def record(self, index: int, wall_s: float | None, warm: bool = True) -> None:
        """Run ``index`` ended after ``wall_s`` wall seconds in its worker.

        :param index: the run's position in the runs given to the constructor
        :param wall_s: its wall time (``None``: unknown, it only counts as done)
        :param warm: whether its worker had run its planner before (a cold run also loaded it: not a sample)
        """
        self.done[index] = True
        if warm and wall_s is not None and np.isfinite(wall_s) and self.seconds[index] > 0:
            self._wall[self.codes[index]] += float(wall_s)
            self._simulated[self.codes[index]] += self.seconds[index]

    def rates(self) -> np.ndarray:
        """Per planner (in :attr:`names` order), wall seconds per simulated second of its warm runs (NaN before its
        first warm run)."""
        measured = self._simulated > 0
        rates = np.divide(self._wall, self._simulated, out=np.full_like(self._wall, np.nan), where=measured)
        return rates

    def remaining_s(self) -> float | None:
        """Expected wall seconds until the last run ends (``None`` while a planner with runs left has no warm run:
        its cost would be a guess from another planner's, the cheap first runs' error this clock avoids)."""
        left = ~self.done
        if not left.any():
            return 0.0
        seconds = np.bincount(self.codes[left], self.seconds[left], minlength=len(self.names))
        rates = self.rates()
        if np.isnan(rates[seconds > 0]).any():
            return None
        cost = float(seconds[seconds > 0] @ rates[seconds > 0])
        return cost / min(self.workers, int(left.sum()))


def interleaved(planners: int, scenarios: int) -> list[int]:
    """The order in which to hand out ``planners x scenarios`` runs (planner-major indices): scenario by
    scenario, every planner in turn, so that every planner's cost is measured among the first runs.

    :param planners: number of planners
    :param scenarios: number of scenarios
    :return: indices ``p * scenarios + s``, for ``s`` in order and ``p`` in order within each ``s``
    """
    return [p * scenarios + s for s in range(scenarios) for p in range(planners)]


def format_eta(seconds: float | None) -> str:
    """``"1:02:03"``/``"02:03"`` as tqdm prints a time, ``"?"`` when unknown."""
    if seconds is None or not np.isfinite(seconds):
        return "?"
    from tqdm import tqdm

    return tqdm.format_interval(max(0.0, seconds))
