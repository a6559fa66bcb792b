"""glide's other parameter sets, as planner classes for ``--planner FILE:CLASS``, to draw its stops-for-delay front.

The shipped ``glide`` uses the values tuned by ``scripts/tune_baselines.py`` for the first-phase control
(docs/baselines.md). These classes keep the hand-set recipe glide started from (window 30 m, floor 2 m/s,
platoon gap 2.5 s, headway 1.0 s, decel 3.0, commit_decel 5.0, stop_penalty 1.9), over the same control,
and glide as first shipped (``GUARDED``: IDM following and AIM's zone guard on its advice)::

    sb3-graph evaluate --planner glide+shield --planner fullthrottle+shield \\
        --planner scripts/glide_variants.py:GlideRecipe+shield \\
        --planner scripts/glide_variants.py:GlideRecipeWhole+shield \\
        --planner scripts/glide_variants.py:GlideGuarded+shield --scenarios 20 --seed 5000 --jobs 2
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from envs.planners.glide import GUARDED, RECIPE, GlidePlanner
from envs.simulation.scene import MINOR


class GlideRecipe(GlidePlanner):
    """glide with :data:`RECIPE` (the arrival-time yardstick's values)."""

    def __init__(self) -> None:
        super().__init__("GlideRecipe", RECIPE)


class GlideRecipeWhole(GlidePlanner):
    """glide with :data:`RECIPE`, advice over the whole approach (no window)."""

    def __init__(self) -> None:
        super().__init__("GlideRecipeWhole", dataclasses.replace(RECIPE, window=math.inf))


class GlideGuarded(GlidePlanner):
    """glide as first shipped (:data:`envs.planners.glide.GUARDED`)."""

    def __init__(self) -> None:
        super().__init__("GlideGuarded", GUARDED)


# Probes of what a learned planner over glide could move (docs/experiments.md, "How much a policy over glide
# can move"): shifts of glide's order (what the "priority" action type does) and a window per vehicle.


class _Probe(GlidePlanner):
    """glide (its tuned values), named after the probe's class."""

    def __init__(self) -> None:
        super().__init__(type(self).__name__)


class _Shifted(_Probe):
    """glide with its order shifted every step by :meth:`shift` [s] per vehicle."""

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self._rng = np.random.default_rng(seed)

    def shift(self, scene) -> np.ndarray:
        raise NotImplementedError

    def act(self, scene) -> np.ndarray:
        if scene.num_vehicles:
            self.set_priority(self.shift(scene))
        return super().act(scene)


class RandomShift5(_Shifted):
    """Every vehicle's key shifted by a uniform draw in +-5 s, anew each step (the priority action's own range)."""

    spread = 5.0

    def shift(self, scene) -> np.ndarray:
        return self._rng.uniform(-self.spread, self.spread, scene.num_vehicles)


class RandomShift20(RandomShift5):
    """As :class:`RandomShift5`, +-20 s."""

    spread = 20.0


class StandingLast(_Shifted):
    """Standing vehicles (below 1 m/s) 20 s later in the order: one that has stopped loses no stop by waiting."""

    later = 20.0

    def shift(self, scene) -> np.ndarray:
        return np.where(scene.speed < 1.0, self.later, 0.0)


class StandingFirst(StandingLast):
    """Standing vehicles 20 s earlier in the order."""

    later = -20.0


class _Widened(_Probe):
    """glide's advice over the whole approach for the vehicles :meth:`wide` selects, its window for the rest."""

    def wide(self, scene) -> np.ndarray:
        raise NotImplementedError

    def advice_window(self, scene) -> np.ndarray:
        return np.where(self.wide(scene), math.inf, self.params.window)


class WideMinor(_Widened):
    """The whole approach for vehicles of the minor road."""

    def wide(self, scene) -> np.ndarray:
        return scene.priority == MINOR


class WideMajor(_Widened):
    """The whole approach for vehicles of the major road."""

    def wide(self, scene) -> np.ndarray:
        return scene.priority != MINOR


class WideAll(_Widened):
    """The whole approach for every vehicle (glide's tuned values otherwise)."""

    def wide(self, scene) -> np.ndarray:
        return np.ones(scene.num_vehicles, bool)


class WideRandom(_Widened):
    """The whole approach for a fixed random half of the vehicles (a hash of the id)."""

    def wide(self, scene) -> np.ndarray:
        return scene.vehicle_id * 2654435761 % 1000 < 500


class GlideSteady(GlidePlanner):
    """glide with hysteresis against perception error: a perceived position within 1 m of the one it planned from,
    driven on, does not move its plans (``GlideParams.hysteresis``; an exact scene is planned as it is)."""

    def __init__(self) -> None:
        super().__init__("GlideSteady", dataclasses.replace(GlidePlanner().params, hysteresis=1.0))


class GlideSteady2(GlidePlanner):
    """:class:`GlideSteady` with a band of 2 m."""

    def __init__(self) -> None:
        super().__init__("GlideSteady2", dataclasses.replace(GlidePlanner().params, hysteresis=2.0))
