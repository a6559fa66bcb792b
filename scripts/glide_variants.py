"""glide with the hand-set values of its first recipe, as planner classes for ``--planner FILE:CLASS``.

The shipped ``glide`` uses the values tuned by ``scripts/tune_baselines.py`` (docs/baselines.md).
These classes keep the recipe glide started from, to compare the two on other scenarios and demand::

    sb3-graph sweep --planner glide+shield --planner fullthrottle+shield \\
        --planner scripts/glide_variants.py:GlideRecipe+shield \\
        --planner scripts/glide_variants.py:GlideRecipeWhole+shield \\
        --demand 0.2 0.35 0.5 --scenarios 8 --seed 5000 --jobs 1
"""

from __future__ import annotations

import dataclasses
import math

from envs.planners.glide import GlideParams, GlidePlanner

# The recipe: advice within 30 m of the line, no cruise below 2 m/s, a follower within 2.5 s of its
# leader batched behind it, 1.0 s headway at the line (the other values as shipped).
RECIPE = GlideParams(window=30.0, floor=2.0, platoon_gap=2.5, follow_headway=1.0)


class GlideRecipe(GlidePlanner):
    """glide with :data:`RECIPE`."""

    def __init__(self) -> None:
        super().__init__("GlideRecipe", RECIPE)


class GlideRecipeWhole(GlidePlanner):
    """glide with :data:`RECIPE`, advice over the whole approach (no window)."""

    def __init__(self) -> None:
        super().__init__("GlideRecipeWhole", dataclasses.replace(RECIPE, window=math.inf))
