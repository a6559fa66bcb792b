"""AIM with full-throttle acceleration, a shorter headway and no zone buffer, to run behind the shield.

A candidate for a planner with full throttle's flow and AIM's stops, tried and dropped:
behind the shield it moves no more than AIM (docs/training.md, "What training has tried"). The command::

    sb3-graph evaluate --planner examples/aim_fast.py:AIMFast+shield \\
        --planner envs/planners/adversarial.py:FullThrottle+shield --planner aim \\
        --scenarios 10 --seed 0 --trust-planner-files
"""

from envs.planners.aim import AIMParams, AIMPlanner


class AIMFast(AIMPlanner):
    """:class:`AIMPlanner` with ``accel=5, decel=3, follow_headway=0.9, buffer=0, stop_penalty=1``."""

    def __init__(self) -> None:
        super().__init__("AIMFast", AIMParams(accel=5.0, decel=3.0, follow_headway=0.9, buffer=0.0, stop_penalty=1.0))
