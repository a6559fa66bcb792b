"""A planner's answer, checked before anything applies it: one clear line when it is not a valid command.

A planner must return one finite acceleration per vehicle, as a numeric array of shape ``(n,)``,
within ``[scene.a_min, scene.a_max]`` (up to :data:`OUTPUT_TOLERANCE`). Anything else (NaN, inf,
a list of strings, an ``(n, 1)`` array, a wrong length, a value far outside the bounds) is a
*planner error*, never clipped or reshaped into something that runs: the evaluation harness marks
the run failed, and the safety shield hands the vehicles concerned (all of them, when the shape or
dtype is wrong) to its fallback for that step, and counts it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.simulation.scene import Scene

# How far outside [a_min, a_max] an acceleration may lie and still count as the bound [m/s^2]
# (rounding of a planner that computes its bound in float32 or through a tanh).
OUTPUT_TOLERANCE = 1e-4


class PlannerError(ValueError):
    """A planner returned something that is not a valid command (or raised).

    :param planner: the planner's report name
    :param scene: the scene it answered
    :param problem: what is wrong, naming the value
    :param rows: ``(n,)`` bool: the vehicles whose values are invalid, when the output has the right
        shape and dtype (``None`` when the whole output is unusable)
    """

    def __init__(self, planner: str, scene: Scene, problem: str, rows: np.ndarray | None = None) -> None:
        self.planner = str(planner)
        self.rows = rows
        self.time = float(scene.time)
        self.step = int(round(scene.time / scene.dt)) if scene.dt > 0 else 0
        self.problem = str(problem)
        self.scenario: str | None = None
        super().__init__(self.line())

    def line(self, scenario: str | None = None) -> str:
        """The one line that reports the error.

        :param scenario: the scenario file the run replayed (default: the one recorded, if any)
        """
        where = scenario if scenario is not None else self.scenario
        at = f", scenario {where}" if where else ""
        return f"planner error: {self.planner}{at}, step {self.step} (t = {self.time:.1f} s): {self.problem}"


def checked_accelerations(
    output: Any, scene: Scene, planner: str, tolerance: float = OUTPUT_TOLERANCE
) -> np.ndarray:
    """A planner's output as the ``(n,)`` float accelerations to apply, or a :class:`PlannerError`.

    :param output: what ``planner.act(scene)`` returned
    :param scene: the scene it answered
    :param planner: the planner's report name (for the message)
    :param tolerance: how far beyond ``[a_min, a_max]`` a value may lie (it is then clipped to the bound) [m/s^2]
    :return: ``(n,)`` float64 accelerations within ``[scene.a_min, scene.a_max]``
    :raises PlannerError: the output is not a valid command
    """
    n = scene.num_vehicles
    expected = f"expected a float array of shape ({n},), one acceleration per vehicle"
    if isinstance(output, (list, tuple)):
        try:
            output = np.asarray(output)
        except (TypeError, ValueError):
            raise PlannerError(planner, scene, f"returned a ragged {type(output).__name__}; {expected}") from None
    if not isinstance(output, np.ndarray):
        raise PlannerError(planner, scene, f"returned {type(output).__name__}; {expected}")
    if output.dtype.kind not in "iuf":
        raise PlannerError(planner, scene, f"returned dtype {output.dtype}; {expected}")
    if output.shape != (n,):
        raise PlannerError(planner, scene, f"returned shape {output.shape}; {expected}")
    acc = output.astype(np.float64)
    bad = ~np.isfinite(acc)
    if not bad.any():
        bad = (acc < scene.a_min - tolerance) | (acc > scene.a_max + tolerance)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise PlannerError(
            planner,
            scene,
            f"acceleration {float(acc[k])!r} for vehicle {int(scene.vehicle_id[k])} (row {k}) is not a finite "
            f"number in [a_min, a_max] = [{scene.a_min:g}, {scene.a_max:g}] m/s^2 ({int(bad.sum())} of {n} vehicles)",
            rows=bad,
        )
    return np.clip(acc, scene.a_min, scene.a_max)
