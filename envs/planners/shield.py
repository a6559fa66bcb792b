"""A safety shield: any planner's accelerations, checked and overridden where needed before they are applied.

The paper leaves the learned planner's rare collisions to a check it does not build ("the
cooperative maneuver will only be advertised to the connected vehicles, if it fulfills sanity
checks like being collision-free"). :class:`Shield` is that check, placed where the paper puts it:
between a planner (on an edge server) and the vehicles. It knows only the scene and the layout,
so it wraps every planner on every layout.

How it decides, every policy step:

1. The planner proposes one acceleration per vehicle.
2. The proposal is applied for one period, then every vehicle follows the *fallback* for the rest
   of the horizon, all predicted with the simulation's own vehicle model
   (:func:`envs.simulation.engine.integrate`: sub-steps, the ±a_max clip, the speed governor).
3. The prediction must be free of conflicts: every follower keeps a gap to the vehicles ahead on
   its path; two vehicles on crossing paths never occupy their conflict zone at the same time;
   two vehicles on merging paths stay a vehicle length apart once they merge. At the end, every
   vehicle has either cleared the intersection or stands still before the zones it does not own.
4. A vehicle whose proposal causes a conflict gets the fallback's command instead (an
   *intervention*); the check repeats until the plan passes.

The fallback is a feedback law of the state alone: a vehicle that can still stop before the first
conflict zone on its route brakes at ``a_max`` (local planning: it stops before zones it does not
own); a vehicle that cannot (it is committed, it owns its zone) or that has cleared the
intersection proceeds at ``proceed_acceleration``, following the vehicles ahead of it with a
responsibility-sensitive safety gap (it can always stop behind a leader braking at ``a_max``), and
waiting before a later zone of its route that a crossing vehicle can no longer stop before or is in
(so that its safety does not rest on predicted timing, which changes when a leader turns off or
merges in). A vehicle that another waits for gets the fallback when the planner would brake it below
it, so that the planner's order of way and the fallback's cannot stand each other off.
Because the plan accepted at one step contains the fallback from the next state, the all-fallback plan
passed the check one step earlier: the shield always has a safe answer (recursive feasibility), and once
the prediction reaches a state where everyone stands or has left, and every follower has room to stop
behind its leader (its gap stays at the check's floor if both brake now), the fallback keeps it that way:
the prediction ends there. (Without the room, a planner that rams a leader past the intersection for one
period leaves a gap that no fallback can keep.) This holds as long as the relations between vehicles stay
as predicted: new vehicles appear far upstream with a braking gap (the simulation's spawn check), and the
leaders the fallback follows are those of the scene, the next vehicle on the same route, the vehicle
ahead on another route from the same spawn lane until the two centre lines part (lanes that split run
side by side for a while: inD), and merges along the common exit lane. Should the fallback still fail, it
is predicted once more over ``drain_horizon`` and taken if it passes then (vehicles tangled in the box,
after such steps, can take longer than ``horizon`` to drain); failing that, every vehicle brakes at
``a_max`` and the step is counted in :attr:`Shield.unresolved`.

Liveness: inside the intersection a planner may not brake a vehicle below :data:`LIVE_SPEED`. A committed
vehicle gets the fallback's command instead, and one past its stop line that has not committed is
proposed onwards (checked like any proposal). Before the line the planner decides, until the junction
stalls: when for ``watchdog_after`` seconds no vehicle entered or left the intersection while vehicles
waited before their lines, a live planner (FIFO by default) proposes instead until traffic moves
(:mod:`envs.planners.watchdog`, docs/shield.md).
An invalid proposal is a planner error (:mod:`envs.planners.errors`), answered with the fallback.

Human drivers (mixed traffic, issue 39; docs/shield.md): they cannot be commanded. Their command for the
first period is the human model's (:func:`envs.planners.human.human_commands`, what the environment will
apply); they are never overridden nor blamed. After it, a human that the priority rules let go and that
is within ``human_lookahead`` seconds plus its comfortable stopping distance (``human_deceleration``) of
its first zone is predicted as committed: it proceeds and does not stop for automated vehicles, which
must keep out of its zones. Every other human is predicted with the fallback (it stops before its zones,
as the priority rules make it yield). Whether a human ends the prediction stuck is not checked.
Drivers of another world (SUMO's) do not drive as the model: a driver seen standing where the model goes waits
(:meth:`Shield._hesitating`), one seen going faster than the model commanded goes (:meth:`Shield._defiant`); the
shield predicts them so, and hands its planner the same view (``Scene.human_intent``). Where no command passes,
it takes the fallback or everyone braking, whichever its prediction shows in fewer conflicts (docs/shield.md).

Only the pairs that can conflict are checked (:meth:`Shield._may_commit`). Vectorized over vehicles
and pairs; the only loops run over the horizon's time steps and over the
few rounds of overrides. The prediction (step 2), the fallback, the scan of a prediction for
conflicts (step 3) and the rules that the liveness checks and the blame read (who is committed, who
waits for whom, who follows whom) run compiled (:mod:`envs.planners._shield_kernel`, numba): the
periods are sequential and the arrays small, so in NumPy the per-call overhead was most of the
shield's cost. The kernels are the only implementation of these rules; ``tests/shield_reference.py``
holds their NumPy form (with :func:`envs.simulation.engine.integrate` itself), the oracle that they match
bit for bit, the blame (who is overridden for a conflict) included.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from envs.planners import _shield_kernel
from envs.planners.base import Planner
from envs.planners.errors import PlannerError, checked_accelerations
from envs.planners.fifo import FIFOPlanner
from envs.planners.human import CRAWL_SPEED, approach_limit, human_commands, human_window
from envs.planners.priority_rules import maneuver_priority
from envs.planners.shield_bounds import ShieldBounds
from envs.planners.watchdog import WATCHDOG_AFTER, WATCHDOG_HOLD, LivenessWatchdog
from envs.simulation.commitment import STANDING, STOP_SLACK
from envs.simulation.faults import ById
from envs.simulation.layouts import ZONE_MARGIN, body_hull, parting_arcs
from envs.simulation.scene import Scene

_INT = np.int64
# Standing speed [m/s] and the stopping slack [m] of the commitment rule (:mod:`envs.simulation.commitment`).
_STANDING = STANDING
_STOP_SLACK = STOP_SLACK
# Liveness: inside the intersection, a planner may slow a vehicle down to this speed but not further
# (below it, the fallback's command or, before the vehicle commits, going on is checked instead) [m/s].
LIVE_SPEED = CRAWL_SPEED  # also the human window's crawl speed
# Planner-error lines a shield keeps per run (the count is complete).
MAX_ERROR_LINES = 5
# On a perceived scene (declared bounds): how much a follow gap below its floor may shrink in a prediction, and the
# room the fallback keeps over its gap margin, for the changes of view from one step to the next [m] (`_view_floors`).
VIEW_SHRINK = 0.5
VIEW_KEEP = 1.0
# ... and how much farther a moving vehicle may be found to stop at the next step than the prediction shows [m].
VIEW_STOP = 4.0
# Rounding allowance on the bound of a vehicle's stopping point over a prediction (`Shield._may_commit`) [m].
_REACH_TOLERANCE = 1e-3


@dataclass
class _Plan:
    """What the check of one scene needs: vehicle rows, their zones and the pairs to check."""

    route: np.ndarray
    arc: np.ndarray
    speed: np.ndarray
    hull_start: np.ndarray  # centre arc from which the body may touch a conflict zone (padded) [m]
    hull_end: np.ndarray  # centre arc past which the body has left every zone (padded) [m]
    follow: np.ndarray  # (k, 2) rows (follower, vehicle ahead on the same path)
    follow_gap: np.ndarray  # (k,) bumper gaps now [m]
    cross: np.ndarray  # (c, 2) rows on crossing routes
    cross_lo: np.ndarray  # (c, 2) occupancy interval of each body's centre arc in the pair's zone
    cross_hi: np.ndarray
    merge: np.ndarray  # (g, 2) rows on merging routes
    merge_lo: np.ndarray  # (g, 2) centre arc from which each has reached the merge zone
    merge_exit: np.ndarray  # (g, 2) exit arcs: arc - exit is a common coordinate after the merge
    merge_sep: np.ndarray  # (g,) smallest centre distance after the merge [m]
    rank: np.ndarray  # (n,) who goes first when two would enter a zone at once: farthest in, then lowest id
    vehicle_id: np.ndarray  # (n,) ids: break ties between two vehicles equally far through one zone
    follow_floor: np.ndarray  # (k,) smallest gap a prediction may leave [m]: half the gap margin, or a short gap now
    # (k,) arc of the vehicle ahead at which a follow pair ends: on another route from the same spawn lane, when
    # its rear passes where the centre lines part (as the simulation's leaders); inf for every other pair
    follow_until: np.ndarray
    # Crossing pairs whose bodies are both in their zone now (after unresolved steps), the one less far
    # through (`cross_back`: column 0 or 1) standing: it must not move (past `cross_stop`).
    cross_already: np.ndarray  # (c,) bool
    cross_back: np.ndarray  # (c,) column of the one behind
    cross_stop: np.ndarray  # (c,) its arc now plus the stopping slack [m]
    human: np.ndarray  # (n,) bool: human drivers (not commanded: their end state is not checked)
    # Crossing pairs of a going human and an automated vehicle: the pair, the human's column and the
    # time window in which the human may be in the pair's zone (`Shield._human_windows`) [s].
    human_pair: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    human_col: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    human_from: np.ndarray = field(default_factory=lambda: np.zeros(0))
    human_until: np.ndarray = field(default_factory=lambda: np.zeros(0))
    committed_now: np.ndarray | None = None  # (n,) bool: Shield.committed in the state now, once computed
    # (n,) each vehicle's zone padding [m]: the shield's zone_margin, 0 for a waiting human (it stands)
    pad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    waiting: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (n,) waiting humans (`_hesitating`)
    # Declared bounds (`Shield._widening`, `Shield._actuation`): (n,) how far each vehicle's true position may lie
    # from the scene's (0: exact), and the actuation model of the prediction (None: commands realised at once).
    widen: np.ndarray | None = None
    follow_keep: np.ndarray | None = None  # (k,) room the fallback keeps to the vehicle ahead over gap_margin [m]
    actuation: _shield_kernel.Actuation | None = None

    def __post_init__(self) -> None:
        # The compiled kernels' view, contiguous and of one dtype per field (one compiled signature);
        # the columns of `follow` and their arcs now apart: the fallback reads them every period.
        i, f = partial(np.ascontiguousarray, dtype=_INT), partial(np.ascontiguousarray, dtype=float)
        follower, ahead = i(self.follow[:, 0]), i(self.follow[:, 1])
        self.kernel_arrays = _shield_kernel.PlanArrays(
            route=i(self.route),
            hull_start=f(self.hull_start),
            hull_end=f(self.hull_end),
            follower=follower,
            ahead=ahead,
            follow_gap=f(self.follow_gap),
            follower_arc=f(self.arc[follower]),
            ahead_arc=f(self.arc[ahead]),
            follow_floor=f(self.follow_floor),
            follow_until=f(self.follow_until),
            follow_keep=f(np.zeros(len(follower)) if self.follow_keep is None else self.follow_keep),
            merge_keep=f(
                np.zeros(len(self.merge)) if self.follow_keep is None else np.full(len(self.merge), VIEW_KEEP)
            ),
            cross=i(self.cross),
            cross_lo=f(self.cross_lo),
            cross_hi=f(self.cross_hi),
            cross_already=np.ascontiguousarray(self.cross_already, dtype=bool),
            cross_back=i(self.cross_back),
            cross_stop=f(self.cross_stop),
            vehicle_id=i(self.vehicle_id),
            merge=i(self.merge),
            merge_lo=f(self.merge_lo),
            merge_exit=f(self.merge_exit),
            merge_sep=f(self.merge_sep),
            # A human driver's model sees a merging vehicle only once it leads on the same lane.
            merge_yields=np.ascontiguousarray(~np.asarray(self.human, bool)),
        )


class Shield(Planner):
    """Wraps a planner so that its commands stay collision-free (see the module docstring).

    The vehicle-model constants must be the simulation's (the defaults are the environment's);
    ``dt`` and ``a_max`` come from each scene.

    :param planner: the planner whose proposals are checked
    :param horizon: longest prediction [s]; the prediction stops earlier once every vehicle
        stands before its zones or has left the intersection
    :param drain_horizon: where no command passes and the whole fallback fails only by leaving a
        vehicle inside the intersection at the horizon's end, the fallback is predicted this long
        [s] and taken if it passes then (``<= horizon``: never; everyone brakes, as on other failures)
    :param zone_margin: padding of every conflict zone on both ends [m]; at least the distance a
        vehicle moves in one simulation sub-step, so that checks at sub-step times see every overlap
    :param gap_margin: bumper gap the fallback keeps to a leader that brakes at ``a_max`` [m]; a
        prediction fails where a gap falls below half of it (a vehicle turning off a shared lane
        swings its rear corner up to ~0.5 m closer than the distance along the path shows)
    :param merge_margin: extra distance between two vehicles on merging paths, over their half lengths [m]
    :param proceed_acceleration: acceleration of the fallback for committed and cleared vehicles [m/s^2]
    :param simulation_frequency: integration rate of the simulation [Hz], for scenes that do not carry theirs
        (``Scene.substeps``: those of a plant do)
    :param max_speed: the simulation's speed cap [m/s]
    :param governor_deceleration: the simulation's speed governor [m/s^2]
    :param name: report name (default: ``<planner name>+shield``)
    :param watchdog_after: the liveness watchdog (:mod:`envs.planners.watchdog`): seconds without a vehicle
        entering or leaving the intersection, while vehicles wait before their lines, after which
        ``live_planner`` proposes instead of ``planner`` (a takeover); ``None``: no watchdog
    :param watchdog_hold: seconds after the first vehicle entered under a takeover before ``planner`` proposes again
    :param live_planner: the planner of a takeover, its proposals checked as any other (default:
        :class:`envs.planners.fifo.FIFOPlanner` with this ``governor_deceleration``)
    :param human_lookahead: a human driver that the priority rules let go is predicted not to stop for
        automated vehicles once it is this many seconds (at its speed), plus its stopping distance at
        ``human_deceleration``, from its first conflict zone [s]
    :param human_deceleration: the braking a human driver is assumed to use at most [m/s^2]
    :param human_margin: seconds added on both sides of the time window in which a going human driver
        may occupy a conflict zone (``_human_windows``); an automated vehicle must keep out of it
    :param bounds: the faults it is declared to tolerate (:class:`envs.planners.shield_bounds.ShieldBounds`;
        ``None``: the exact world)
    :param human_hesitation: a human driver that stands (below ``human_standing`` [m/s]) this long [s] while the
        human model lets it go waits for another vehicle (a driver of another world, e.g. SUMO's): it is predicted
        standing until it moves (:meth:`_hesitating`)
    :param human_standing: see ``human_hesitation`` [m/s]
    :param human_tolerance: a human driver whose speed after a period exceeds the one the human model commanded by
        more than this [m/s] does not yield as the model does: for ``human_memory`` seconds after, it is predicted
        going (:meth:`_defiant`)
    :param human_memory: see ``human_tolerance`` [s]
    """

    def __init__(
        self,
        planner: Planner,
        horizon: float = 8.0,
        drain_horizon: float = 24.0,
        zone_margin: float = ZONE_MARGIN,
        gap_margin: float = 2.0,
        merge_margin: float = 2.0,
        proceed_acceleration: float = 3.0,
        simulation_frequency: int = 15,
        max_speed: float = 20.0,
        governor_deceleration: float = 3.0,
        name: str | None = None,
        watchdog_after: float | None = WATCHDOG_AFTER,
        watchdog_hold: float = WATCHDOG_HOLD,
        live_planner: Planner | None = None,
        human_lookahead: float = 3.0,
        human_deceleration: float = 2.0,
        human_margin: float = 1.0,
        bounds: ShieldBounds | None = None,
        human_hesitation: float = 1.0,
        human_standing: float = 0.1,
        human_tolerance: float = 0.3,
        human_memory: float = 3.0,
    ) -> None:
        super().__init__(name or f"{planner.name}+shield")
        self.bounds = bounds if bounds is not None else ShieldBounds()
        self.human_lookahead = float(human_lookahead)
        self.human_deceleration = float(human_deceleration)
        self.human_margin = float(human_margin)
        self.human_hesitation = float(human_hesitation)
        self.human_standing = float(human_standing)
        self.human_tolerance = float(human_tolerance)
        self.human_memory = float(human_memory)
        self._forget_humans()
        self.planner = planner
        self.watchdog = None if watchdog_after is None else LivenessWatchdog(watchdog_after, watchdog_hold)
        self.live_planner = (
            live_planner if live_planner is not None else FIFOPlanner(governor_deceleration=governor_deceleration)
        )
        self.horizon = float(horizon)
        self.drain_horizon = float(drain_horizon)
        self.zone_margin = float(zone_margin)
        self.gap_margin = float(gap_margin)
        self.merge_margin = float(merge_margin)
        self.proceed_acceleration = float(proceed_acceleration)
        self.simulation_frequency = int(simulation_frequency)
        self.max_speed = float(max_speed)
        self.governor_deceleration = float(governor_deceleration)
        self.interventions = 0
        self.vehicle_steps = 0
        self.unresolved = 0
        self.planner_errors = 0
        self.errors: list[PlannerError] = []
        self.last_overridden = np.zeros(0, bool)
        self._stuck_only = False  # the last check failed only by a vehicle left inside at the horizon's end
        self._prune = True  # only the pairs that can conflict (`_may_commit`); False: every pair (tests, benchmarks)

    # ------------------------------------------------------------------ planner face
    def reset(self, seed: int | None = None) -> None:
        """Reset the wrapped planner, the live planner, the watchdog and the intervention counters."""
        self.planner.reset(seed)
        self.live_planner.reset(seed)
        if self.watchdog is not None:
            self.watchdog.reset()
        self.interventions = 0
        self.vehicle_steps = 0
        self.unresolved = 0
        self.planner_errors = 0
        self.errors = []
        self._forget_humans()

    def _forget_humans(self) -> None:
        """What the shield has seen the human drivers do (a run's memory, kept by vehicle id)."""
        self._stood = ById()  # humans standing against the model: since when [s] (`_hesitating`)
        self._seen = ById()  # the last scene's vehicles: speeds, model commands, last defiance [s] (`_defiant`)
        self._seen_time = -np.inf
        self._view: tuple | None = None  # (scene, `_human_view` of it)
        self._yields = np.zeros(0, _INT)  # waiting humans and the vehicles they wait for (`_keeps_windows`), as keys

    @property
    def error_lines(self) -> list[str]:
        """The first planner errors of the run (at most :data:`MAX_ERROR_LINES`), one line each."""
        return [error.line() for error in self.errors]

    def stats(self) -> dict[str, float]:
        """The wrapped planner's counters (:meth:`Planner.stats`) and the shield's since the last reset:
        interventions and the vehicle-steps they are a share of, unresolved steps (everyone braked), planner
        errors (steps), the watchdog's takeovers and the vehicle-steps under them (0 without a watchdog)."""
        watchdog = self.watchdog
        return {
            **self.planner.stats(),  # the wrapped planner's own counters (a search's fallbacks ...)
            "shield_interventions": self.interventions,
            "shield_vehicle_steps": self.vehicle_steps,
            "shield_unresolved": self.unresolved,
            "planner_errors": self.planner_errors,
            "watchdog_takeovers": 0 if watchdog is None else watchdog.takeovers,
            "watchdog_vehicle_steps": 0 if watchdog is None else watchdog.vehicle_steps,
        }

    @property
    def intervention_rate(self) -> float:
        """Share of vehicle-steps whose command the shield replaced since the last reset (``nan`` if none)."""
        return self.interventions / self.vehicle_steps if self.vehicle_steps else float("nan")

    def act(self, scene: Scene) -> np.ndarray:
        """The wrapped planner's proposal for a private copy of the scene, checked on the shield's own.

        While the watchdog's takeover lasts (:mod:`envs.planners.watchdog`), the live planner proposes
        instead (the wrapped planner is not called).

        An invalid proposal (:func:`envs.planners.errors.checked_accelerations`) is a planner error,
        counted in :attr:`planner_errors` (the first ones in :attr:`errors`): the vehicles with a
        non-finite or out-of-bounds value, or all of them when the shape or dtype is wrong, get the
        fallback for this step (counted as interventions); the other values are checked as usual.
        """
        planner = self.live_planner if self.watchdog is not None and self.watchdog.observe(scene) else self.planner
        mine = scene.copy()
        if scene.humans.any():  # what the shield has seen the human drivers do, for the planner too
            mine = replace(mine, human_intent=self._human_view(scene)[3])
        return self.check_output(scene, planner.act(mine), planner.name)

    def check_output(self, scene: Scene, output: object, planner: str) -> np.ndarray:
        """:meth:`act` for a proposal already made: a planner's raw output checked as a command (a planner error
        answered with the fallback, see :meth:`act`), then checked for conflicts (:meth:`check`). A caller that
        trusts its planner not to write in the scene (``lookahead``'s rollouts) saves :meth:`act`'s copy of it.

        :param scene: the scene the planner answered
        :param output: what its ``act`` returned
        :param planner: its report name (for a planner error's line)
        :return: ``(n,)`` accelerations to apply
        """
        n = scene.num_vehicles
        try:
            proposal = checked_accelerations(output, scene, planner)
        except PlannerError as error:
            self.planner_errors += 1
            if len(self.errors) < MAX_ERROR_LINES:
                self.errors.append(error)
            if error.rows is None:
                return self.check(scene, np.zeros(n), forced=np.ones(n, bool))
            return self.check(scene, np.where(error.rows, 0.0, np.asarray(output, float)), forced=error.rows)
        return self.check(scene, proposal)

    def check(self, scene: Scene, proposal: np.ndarray, forced: np.ndarray | None = None) -> np.ndarray:
        """The safe version of a proposal: ``proposal`` where it passes, the fallback where it does not.

        Records the overridden vehicles in :attr:`last_overridden` and the counters.

        :param scene: the vehicles now (must carry ``layout`` and ``arc``)
        :param proposal: ``(n,)`` proposed accelerations [m/s^2]
        :param forced: ``(n,)`` bool: vehicles that get the fallback whatever they were proposed
            (counted as overridden); default none
        :return: ``(n,)`` accelerations to apply
        """
        n = scene.num_vehicles
        acc = np.clip(np.asarray(proposal, dtype=float).reshape(n), scene.a_min, scene.a_max)
        forced = np.zeros(n, bool) if forced is None else np.asarray(forced, bool).reshape(n)
        self.last_overridden = np.zeros(n, bool)
        if n == 0:
            return acc
        if scene.layout is None or scene.arc is None:
            raise ValueError("the shield needs the scene's layout and arcs (scenes built by the simulation have them)")
        human = scene.humans
        going = np.zeros(n, bool)
        waiting = np.zeros(n, bool)
        if human.any():  # what they will do, whatever is proposed: never overridden, never blamed
            human_acc, going, waiting, _ = self._human_view(scene)
            acc = np.where(human, np.clip(human_acc, scene.a_min, scene.a_max), acc)
            forced = forced & ~human
        plan = self._plan(scene, going, waiting)
        if going.any() or waiting.any():
            self._human_windows(scene, plan, going, waiting)
        fallback = self._fallback(scene, plan, plan.arc, plan.speed)
        if plan.widen is not None:  # a perceived scene: what its changes of view leave the fallback unable to keep
            forced = forced | (self._tolerate(scene, plan, np.where(human, acc, fallback)) & ~human)
        acc = np.where(forced, fallback, acc)
        # Liveness: a vehicle past its stop line that the proposal brakes is proposed onwards instead
        # (checked like any proposal: where going on conflicts, the fallback brakes it).
        lifted = self._parked_past_the_line(scene, plan, acc) & ~forced & ~human
        acc = np.where(lifted, min(self.proceed_acceleration, float(scene.a_max)), acc)
        capped = np.zeros(n, bool)
        if human.any():  # behind a human: keep a gap from which it can stop if the human brakes hard
            cap = self._behind_human_cap(scene, human, human_acc)
            capped = acc > cap + 1e-9
            acc, fallback = np.minimum(acc, cap), np.minimum(fallback, cap)
        deviates = (np.abs(acc - fallback) > 1e-9) & ~human
        overridden = forced | self._awaited_and_braked(scene, plan, acc, fallback)
        overridden |= self._committed_and_braked(scene, plan, acc, fallback)
        overridden &= ~human
        command = acc
        for _ in range(n + 1):
            command = np.where(overridden, fallback, acc)
            blamed = self._blame(scene, plan, command, deviates & ~overridden)
            if blamed is None:
                break
            if not blamed.any():  # a conflict no single proposal explains: take the whole fallback
                blamed = deviates & ~overridden
            if not blamed.any():
                # The fallback itself fails. Where it only does not finish within the horizon (a
                # tangle in the box that drains slowly: a vehicle still inside at the end), a longer
                # look can show it finish; braking everyone would keep that vehicle inside for good.
                # (A longer prediction repeats the shorter one's first rows, so only a failure that
                # was no conflict but a vehicle left inside can pass it: only then is it tried.)
                if (
                    self._stuck_only
                    and self.drain_horizon > self.horizon
                    and self._blame(scene, plan, command, np.zeros(n, bool), self.drain_horizon) is None
                ):
                    break
                # Else (the leader relations it follows changed since the last step, a human did what the
                # model did not predict, or the scene started unsafe): the fallback or everyone braking,
                # whichever the prediction shows in fewer conflicts. Counted in `unresolved`.
                self.unresolved += 1
                command = self._least_bad(
                    scene, plan, np.where(human, acc, fallback), np.where(human, acc, scene.a_min)
                )
                overridden = forced | (np.abs(acc - command) > 1e-9)
                break
            overridden |= blamed & ~human
        overridden = overridden | lifted | capped
        self.last_overridden = overridden
        self.interventions += int(overridden.sum())
        self.vehicle_steps += n - int(human.sum())
        return command

    def _human_view(self, scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The human drivers as the shield predicts them: the model's commands (:func:`human_commands`) corrected by
        what they did (:meth:`_defiant`, :meth:`_hesitating`); once per scene (:meth:`act` and :meth:`check` share it).

        :return: ``(n,)`` first-period commands, ``(n,)`` bool going, ``(n,)`` bool waiting (standing) and ``(n,)``
            int8 :attr:`Scene.human_intent`
        """
        if self._view is not None and self._view[0] is scene:
            return self._view[1]
        human_acc, going = human_commands(scene)
        defiant = scene.humans & self._defiant(scene, human_acc) & ~going
        going = going | defiant
        waiting = self._hesitating(scene, going, human_acc)
        going &= ~waiting
        intent = np.where(waiting, -1, np.where(defiant, 1, 0)).astype(np.int8)
        view = (np.where(waiting, np.minimum(human_acc, 0.0), human_acc), going, waiting, intent)
        self._view = (scene, view)
        return view

    def _least_bad(self, scene: Scene, plan: _Plan, fallback: np.ndarray, brake: np.ndarray) -> np.ndarray:
        """Where no command passes: the fallback, unless everyone braking leaves fewer conflicting pairs in the
        prediction. Braking everyone stops a committed vehicle inside a zone in the path of a human who goes,
        and a follower close behind a leader that its gap counted on to drive on; the fallback clears the box."""
        counts = []
        for command in (fallback, brake):
            arc, speed = self.predict(scene, plan, command)
            follow, cross, merge, _ = self._conflicts(scene, plan, arc, speed)
            human = self._in_human_windows(scene, plan, arc) if plan.human_pair.size else np.zeros(0, bool)
            counts.append(int(follow.sum() + cross.sum() + merge.sum() + human.sum()))
        return brake if counts[1] < counts[0] else fallback

    def _defiant(self, scene: Scene, human_acc: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: human drivers that went faster in the last period than the human model commanded them
        (by more than ``human_tolerance`` m/s), or did within ``human_memory`` seconds. The model's yielding is not
        theirs: they are predicted going (with their windows), whatever the model says now. A driver of the model's
        own world never is (its command is the model's)."""
        now, dt = float(scene.time), float(scene.dt)
        ids, speed, seen = np.asarray(scene.vehicle_id, dtype=_INT), np.asarray(scene.speed, float), self._seen
        rows, found = seen.find(ids)
        defiant_at = seen.get("defiant_at", rows, found, -np.inf)
        if 0.0 < now - self._seen_time <= 1.5 * dt:
            last_speed, last_acc = seen.get("speed", rows, found, 0.0), seen.get("command", rows, found, 0.0)
            expected = np.maximum(last_speed + last_acc * (now - self._seen_time), 0.0)
            defiant_at[found & scene.humans & (speed > expected + self.human_tolerance)] = now
        seen.store(ids, speed=speed, command=human_acc, defiant_at=defiant_at)
        self._seen_time = now
        return scene.humans & (now - defiant_at <= self.human_memory)

    def _hesitating(self, scene: Scene, going: np.ndarray, human_acc: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: human drivers that wait although the human model lets them go: they have stood (below
        ``human_standing``) for ``human_hesitation`` seconds while the model accelerated them. Drivers of another
        world do (SUMO's left-turner waits inside the junction for oncoming traffic, its minor-road driver for a
        major-road vehicle that stands); the model's own drivers never do. A waiting driver is predicted to stay
        where it stands (it goes again only when its foes let it, as it waited for them), with its zones unpadded:
        predicting it going would hold the vehicles it waits for, and both would stand for good.
        (The time each has waited is kept by vehicle id from scene to scene.)"""
        now = float(scene.time)
        ids = np.asarray(scene.vehicle_id, dtype=_INT)
        stands = going & (np.asarray(scene.speed, float) < self.human_standing) & (human_acc > 0.0)
        rows, found = self._stood.find(ids)
        # A scene from before (a rollout's): the wait starts again.
        start = np.minimum(self._stood.get("since", rows, found, now), now)
        self._stood.store(ids[stands], since=start[stands])
        return stands & (now - start >= self.human_hesitation - 1e-9)

    def _behind_human_cap(self, scene: Scene, human: np.ndarray, human_acc: np.ndarray) -> np.ndarray:
        """``(n,)`` the highest acceleration of an automated vehicle in a queue behind a human driver
        (``inf`` for the others): after one period at it, the vehicle can still stop ``gap_margin``
        behind its leader if the leader brakes at ``-a_min`` from then on (a human leader's command
        for the period is known; an automated leader in such a queue is assumed to brake at ``a_min``
        in it too). The prediction cannot hold a human to a plan, so the follow check, which compares
        predicted motions, would let an automated vehicle close up on a human who slows down, and the
        vehicles behind it on it when it is then made to brake.
        """
        n = scene.num_vehicles
        cap = np.full(n, np.inf)
        lead = np.asarray(scene.leader)
        has = lead >= 0
        queued = np.zeros(n, bool)  # somewhere behind a human on the same path
        queued[has] = human[lead[has]]
        for _ in range(n):  # a queue is at most n long; each pass follows one more leader
            more = queued.copy()
            more[has] |= queued[lead[has]] & ~human[lead[has]]
            if np.array_equal(more, queued):
                break
            queued = more
        f = np.flatnonzero(queued & ~human)
        if f.size == 0:
            return cap
        h, dt, brake = lead[f], float(scene.dt), -float(scene.a_min)
        vh = np.asarray(scene.speed, float)[h]
        lead_acc = np.where(human[h], np.clip(human_acc[h], scene.a_min, scene.a_max), scene.a_min)
        vh1 = np.maximum(vh + lead_acc * dt, 0.0)
        room = np.asarray(scene.gap, float)[f] + 0.5 * (vh + vh1) * dt + vh1**2 / (2 * brake) - self.gap_margin
        v = np.asarray(scene.speed, float)[f]
        # v dt + a dt^2 / 2 + (v + a dt)^2 / (2 brake) <= room, solved for a
        qa, qb, qc = dt**2 / (2 * brake), 0.5 * dt**2 + v * dt / brake, v * dt + v**2 / (2 * brake) - room
        disc = qb**2 - 4 * qa * qc
        top = (-qb + np.sqrt(np.maximum(disc, 0.0))) / (2 * qa)
        cap[f] = np.where(disc >= 0, np.clip(top, scene.a_min, np.inf), scene.a_min)
        return cap

    def _parked_past_the_line(self, scene: Scene, plan: _Plan, acc: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: vehicles whose front is past their stop line, that have not yet committed
        (they can still stop before their first zone: the fallback would hold them there too) and that
        the proposal brakes below :data:`LIVE_SPEED`. A planner may hold vehicles before the line, not
        inside the intersection."""
        go = self._committed_now(plan, float(scene.a_max))
        return (np.asarray(scene.dist_to_entry) < 0) & ~go & (acc < 0) & self._slowed_to_a_crawl(scene, plan, acc)

    def _slowed_to_a_crawl(self, scene: Scene, plan: _Plan, acc: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: the proposal leaves the vehicle below :data:`LIVE_SPEED` after this period."""
        return plan.speed + acc * float(scene.dt) < LIVE_SPEED

    def _committed_and_braked(self, scene: Scene, plan: _Plan, acc: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: committed vehicles (:meth:`committed`: they can no longer stop before their first
        zone, or have cleared them all) that the proposal brakes below the fallback and below
        :data:`LIVE_SPEED`. They get the fallback, so that the box always drains: a planner may hold
        vehicles before the line, never inside the intersection or on the exit lanes that the vehicles
        behind them must reach (the fallback itself brakes where safety needs it, and the check still
        runs on the result)."""
        go = self._committed_now(plan, float(scene.a_max))
        return go & (acc < np.minimum(fallback, 0.0) - 1e-9) & self._slowed_to_a_crawl(scene, plan, acc)

    def _awaited_and_braked(self, scene: Scene, plan: _Plan, acc: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: vehicles that another one waits for (:func:`envs.planners._shield_kernel.waits`:
        the fallback holds a committed crossing vehicle for them) and that the proposal brakes
        below the fallback. They get the fallback: a planner that stops a vehicle in a zone while the
        fallback holds a crossing vehicle for it would otherwise keep both standing (a standoff of
        the planner's order of way against the shield's)."""
        awaited = np.zeros(scene.num_vehicles, bool)
        if plan.cross.size:
            a_max = float(scene.a_max)
            go = self._committed_now(plan, a_max)
            arc, speed = np.ascontiguousarray(plan.arc), self._reach_now(plan, a_max)
            waits = _shield_kernel.waits(plan.kernel_arrays, arc, speed, go, a_max, _STANDING, _STOP_SLACK)
            awaited[plan.cross[:, ::-1][waits]] = True
        return awaited & (acc < np.minimum(fallback, 0.0) - 1e-9)

    # ------------------------------------------------------------------ scene -> plan
    def _plan(self, scene: Scene, going: np.ndarray | None = None, waiting: np.ndarray | None = None) -> _Plan:
        lay, route, length = scene.layout, scene.route, scene.length
        arc, speed = np.asarray(scene.arc, float), np.asarray(scene.speed, float)
        m = self.zone_margin
        hull_start, hull_end = body_hull(lay, route, length, m)
        pad = np.full(len(arc), m)
        waiting = np.zeros(len(arc), bool) if waiting is None else waiting
        if waiting.any():
            # A waiting human stands: the padding, which covers a sub-step's travel, would put one that
            # waits at the edge of a zone in it (SUMO's left-turners wait there) and block the zone for good.
            # It stays where it stands: before its first zone for the rules (that a zone it is past begins behind
            # it would have it committed, and the fallback would drive it on).
            pad[waiting] = 0.0
            stop = arc + speed**2 / (2 * float(scene.a_max)) + 2 * _STOP_SLACK
            hull_start = np.where(waiting, np.maximum(hull_start + m, stop), hull_start)
        if going is not None and going.any():
            # A human that goes and is near its zones: predicted as committed (the kernels' rule), by
            # moving its first zone behind it; it then proceeds and the others keep out of its zones.
            near = arc + speed * self.human_lookahead + speed**2 / (2 * self.human_deceleration) + _STOP_SLACK
            hull_start = np.where(going & (near > hull_start), np.minimum(hull_start, arc - 1.0), hull_start)
        # Same path: the leader and the leader's leader (a leader that turns off a shared lane
        # uncovers the next one); the next vehicle ahead on the same route, which the lane's leaders
        # miss where lanes split (on inD a vehicle ahead on a turn lane is no one's leader until the
        # split); a vehicle ahead on another route from the same spawn lane, until its rear has passed
        # where the two centre lines part (inD: lanes that split at 50 m run side by side to 69 m).
        # Conflicting routes: crossing pairs by zone occupancy, merging pairs by a common coordinate;
        # only the pairs that can conflict within the prediction (`_may_commit`, and crossing pairs
        # of which neither has passed the zone). Compiled (`_shield_kernel.pairs`): in NumPy, building
        # and scanning the (n, n) arrays took some 40 calls, a tenth of a shielded step at 100 vehicles.
        widen = self._widening(scene)
        if widen is not None:  # what the scene can be wrong about: every zone and hull grows by it
            hull_start, hull_end, pad = hull_start - widen, hull_end + widen, pad + widen
        candidate = self._may_commit(scene, arc, speed, hull_start) if self._prune else np.ones(len(arc), bool)
        candidate = candidate | waiting  # it stands in the prediction, but keeps windows (`_human_windows`)
        (follow, follow_gap, cross, cross_lo, cross_hi, already, back, stop, merge, merge_lo, merge_exit, merge_sep,
         rank) = _shield_kernel.pairs(
            np.ascontiguousarray(route, dtype=_INT), np.ascontiguousarray(arc), np.ascontiguousarray(speed),
            np.ascontiguousarray(length, dtype=float),
            np.ascontiguousarray(scene.gap, dtype=float), np.ascontiguousarray(scene.leader, dtype=_INT),
            np.ascontiguousarray(scene.vehicle_id, dtype=_INT), np.ascontiguousarray(hull_start, dtype=float),
            candidate, self._prune, lay.conflicts, _merging_routes(lay), parting_arcs(lay), lay.zone_start,
            lay.zone_end, lay.exit_arc, pad, self.merge_margin, _STANDING, _STOP_SLACK,
        )  # fmt: skip
        floor = np.minimum(0.5 * self.gap_margin, follow_gap - 1e-6)  # a short gap may not shrink
        keep = None
        if widen is not None:  # a gap may be shorter, and a merge closer, by both vehicles' widening
            follow_gap = follow_gap - widen[follow[:, 0]] - widen[follow[:, 1]]
            merge_sep = merge_sep + widen[merge[:, 0]] + widen[merge[:, 1]]
            floor, keep = self._view_floors(follow_gap, widen[follow[:, 0]] + widen[follow[:, 1]])
        return _Plan(
            widen=widen,
            follow_keep=keep,
            actuation=self._actuation(scene),
            human=scene.humans,
            pad=pad,
            waiting=waiting,
            route=route,
            arc=arc,
            speed=speed,
            hull_start=hull_start,
            hull_end=hull_end,
            follow=follow,
            follow_gap=follow_gap,
            cross=cross,
            cross_lo=cross_lo,
            cross_hi=cross_hi,
            merge=merge,
            merge_lo=merge_lo,
            merge_exit=merge_exit,
            merge_sep=merge_sep,
            rank=rank,
            vehicle_id=np.asarray(scene.vehicle_id),
            follow_floor=floor,
            cross_already=already,
            cross_back=back,
            cross_stop=stop,
            follow_until=_follow_until(lay, route, length, follow),
        )

    def _human_windows(self, scene: Scene, plan: _Plan, going: np.ndarray, waiting: np.ndarray) -> None:
        """The time windows of the going human drivers in the zones they share with automated vehicles
        (into ``plan``): from the earliest entry (accelerating at IDM's ``acc_max`` up to the highest lane
        limit before the zone, :func:`~envs.planners.human.approach_limit`; now if already in) to the
        latest exit at its speed now (at least ``CRAWL_SPEED``), widened by ``human_margin`` on both
        sides; the whole horizon for a human at a crawl; a waiting human's windows: :meth:`_keeps_windows`."""
        cross, human = plan.cross, plan.human
        may_go = going[cross]
        if waiting.any():
            may_go |= self._keeps_windows(scene, plan, waiting)
        mixed = may_go.any(axis=1) & ~human[cross].all(axis=1)
        pair = np.flatnonzero(mixed)
        if pair.size == 0:
            return
        col = np.where(may_go[pair, 0], 0, 1)
        h = cross[pair, col]
        x0, v = plan.arc[h], plan.speed[h]
        lo, hi = plan.cross_lo[pair, col], plan.cross_hi[pair, col]
        limit = approach_limit(scene, h, lo - x0)
        plan.human_pair, plan.human_col = pair, col
        plan.human_from, plan.human_until = human_window(lo - x0, hi - x0, v, limit, self.human_margin, self.horizon)

    def _keeps_windows(self, scene: Scene, plan: _Plan, waiting: np.ndarray) -> np.ndarray:
        """``(c, 2)`` bool: crossing pairs in whose zone a waiting human (:meth:`_hesitating`, the column) keeps a
        window, as if it went. A waiting human waits for the vehicles of higher precedence
        (:func:`~envs.planners.priority_rules.maneuver_priority`), not for the others, except an automated vehicle
        that stands past its stop line while the human waits (it waits for that one: both stood, and would for
        good); such a pair is remembered (by ids) while the human waits, so that the vehicle, once it moves, is
        not held again in the middle of the box."""
        cross = plan.cross
        rank = maneuver_priority(scene.priority, scene.maneuver)[cross]
        keeps = waiting[cross] & (rank <= rank[:, ::-1])
        other = cross[:, ::-1]
        ids = np.asarray(scene.vehicle_id, dtype=_INT)
        key = ids[cross] * (1 << 32) + ids[other]  # (human, the other) where the column is the human
        inside = (np.asarray(scene.dist_to_entry)[other] < 0) & ~plan.human[other]
        stands = plan.speed[other] < self.human_standing
        yields = keeps & inside & (stands | np.isin(key, self._yields))
        self._yields = np.unique(key[yields])
        return keeps & ~yields

    def _in_human_windows(self, scene: Scene, plan: _Plan, arc: np.ndarray) -> np.ndarray:
        """``(p,)`` bool: the automated vehicle of a human pair is predicted in the pair's zone within
        the human's window (``arc``: the prediction's arcs, row 0 now)."""
        substeps = self.substeps(scene)
        t = np.arange(arc.shape[0]) * (float(scene.dt) / substeps)  # (T + 1,)
        pair, other = plan.human_pair, 1 - plan.human_col
        a = plan.cross[pair, other]
        x = arc[:, a]  # (T + 1, p)
        inside = (x > plan.cross_lo[pair, other]) & (x < plan.cross_hi[pair, other])
        during = (t[:, None] >= plan.human_from) & (t[:, None] <= plan.human_until)
        return (inside & during).any(axis=0)

    def _may_commit(self, scene: Scene, arc: np.ndarray, speed: np.ndarray, hull_start: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: vehicles that may commit within a prediction; the others meet no one in it.

        A prediction applies a command of at most ``a_max`` for one period, then the fallback, which
        brakes at ``a_max`` every vehicle that has not committed. A vehicle's stopping point
        ``x + v^2 / (2 a_max)`` grows by less than ``x0 + v0 dt + a_max dt^2 / 2 + (v0 + a_max dt)^2 /
        (2 a_max)`` over the first period (caps and the governor only lower speeds) and does not grow
        under braking (the simulation's trapezoid sub-steps keep it exactly, up to ``a_max h^2 / 8``
        at the sub-step that stops the vehicle, inside ``_STOP_SLACK``). Where that bound plus the
        slack stays before the vehicle's first zone (``hull_start``), it can stop before every zone
        at every predicted state: it never commits, never enters a zone and never waits for a
        crossing vehicle, and no crossing vehicle waits for it (it can always stop) nor follows it
        at a merge (it neither proceeds nor reaches the merge). Its crossing and merging pairs then
        change nothing in the prediction, the fallback or the check, and are left out (its follow
        pairs stay: its proposal can still close a gap). ``tests/test_shield.py`` checks that the
        shield's commands are bitwise those without the pruning.
        """
        a_max, dt = float(scene.a_max), float(scene.dt)
        v1 = speed + a_max * dt
        lag = self._lag_reach(scene)
        if lag > 0:  # under latency and lag, braking from a realised acceleration of up to a_max (`reach_speeds`)
            v1 = v1 + 2 * a_max * lag
        reach = arc + speed * dt + 0.5 * a_max * dt * dt + v1 * v1 / (2 * a_max)
        return reach + _STOP_SLACK + _REACH_TOLERANCE > hull_start

    # ------------------------------------------------------------------ the declared bounds
    def _widening(self, scene: Scene) -> np.ndarray | None:
        """``(n,)`` how far each vehicle's true position may lie from a perceived scene's [m], ``None`` for an exact
        scene (one without ``arc_std``: it costs nothing) or bounds without a position or speed error: the position
        bound, plus what the speed bound reaches over the age of the state the estimate rests on (``Scene.age``; a
        tracker's estimate of a held state is driven on by the vehicle's commands, off by at most its speed error)."""
        bounds = self.bounds
        if scene.arc_std is None or not (bounds.position > 0 or bounds.speed > 0):
            return None
        age = np.zeros(scene.num_vehicles) if scene.age is None else np.asarray(scene.age, float)
        return bounds.position + bounds.speed * np.minimum(age, bounds.age)

    def _lag_reach(self, scene: Scene) -> float:
        """Latency plus lag [s] that the prediction models for a scene: the declared ones where the scene carries the
        realised accelerations (``Scene.acceleration``: the planner side replays its commands through latency and
        lag), else 0 (every command realised at once, as an exact scene says)."""
        if scene.acceleration is None:
            return 0.0
        return self.bounds.lag + self.bounds.latency

    def _actuation(self, scene: Scene) -> _shield_kernel.Actuation | None:
        """The prediction's actuation model (:class:`envs.planners._shield_kernel.Actuation`), ``None`` where commands
        are realised at once (:meth:`_lag_reach` is 0): the realised accelerations and the commands in flight of the
        scene, the declared latency and lag, at the prediction's sub-steps (as the plant's
        :class:`envs.simulation.faults.Actuator`)."""
        if self._lag_reach(scene) <= 0:
            return None
        lag, latency = self.bounds.lag, self.bounds.latency
        substeps = self.substeps(scene)
        h = float(scene.dt) / substeps
        decay = math.exp(-h / lag) if lag > 0 else 0.0
        realised = np.ascontiguousarray(scene.acceleration, dtype=float)
        previous = realised if scene.command is None else np.ascontiguousarray(scene.command, dtype=float)
        return _shield_kernel.Actuation(
            realised=realised,
            previous=previous,
            old_share=np.clip((latency - np.arange(substeps) * h) / h, 0.0, 1.0),
            decay=decay,
            mean_share=lag / h * (1.0 - decay) if lag > 0 else 0.0,
            lag=lag,
            latency=latency,
            margin=VIEW_STOP,
        )

    def _view_floors(self, follow_gap: np.ndarray, widen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The follow pairs' floors and the room their fallback keeps over ``gap_margin`` on a perceived scene (the
        gaps already shortened by both vehicles' widening, ``widen``). A perceived gap changes from one step to the
        next by more than the vehicles move (the errors drift): a gap below the floor may shrink by
        :data:`VIEW_SHRINK` rather than not at all, though never below the floor of the exact world on the
        perceived gap; and the fallback keeps :data:`VIEW_KEEP` more room, which the next view may take."""
        floor = np.maximum(np.minimum(0.5 * self.gap_margin, follow_gap - VIEW_SHRINK), 0.5 * self.gap_margin - widen)
        return np.minimum(floor, follow_gap - 1e-6), np.full(len(follow_gap), VIEW_KEEP)

    def _tolerate(self, scene: Scene, plan: _Plan, fallback: np.ndarray) -> np.ndarray:
        """Where the fallback itself leaves a follow gap below its floor in the prediction (a perceived scene's view of
        two braking vehicles changes from step to step by what the bounds allow, and the plan accepted at the last
        step no longer shows the gap kept), a proposal may not close it further than the fallback does: the floor
        of such a pair becomes the smallest gap of the fallback's prediction. Without it one such pair, which no
        command can help, would override every vehicle's proposal with the fallback. The followers of such pairs
        get the fallback (returned, ``(n,)`` bool): a floor lowered so must not let a proposal close the gap further,
        step after step.
        """
        follower = np.zeros(len(plan.arc), bool)
        if not (len(plan.follow) or len(plan.merge)):
            return follower
        arc, _ = self.predict(scene, plan, fallback)
        f, ahead = plan.follow[:, 0], plan.follow[:, 1]
        gap = plan.follow_gap + (arc[1:, ahead] - plan.arc[ahead]) - (arc[1:, f] - plan.arc[f])
        gap = np.where(arc[1:, ahead] < plan.follow_until, gap, np.inf).min(axis=0)
        low = gap < plan.follow_floor
        if low.any():
            follower[f[low]] = True
            plan.follow_floor = np.where(low, gap - 1e-6, plan.follow_floor)
            plan.kernel_arrays = plan.kernel_arrays._replace(follow_floor=np.ascontiguousarray(plan.follow_floor))
        if len(plan.merge):  # a merging pair: its separation, once both have reached the merge
            x = arc[1:][:, plan.merge]
            reached = (x > plan.merge_lo).all(axis=2)
            e = x - plan.merge_exit
            distance = np.where(reached, np.abs(e[..., 0] - e[..., 1]), np.inf).min(axis=0)
            close = distance < plan.merge_sep
            if close.any():
                behind = np.where(e[0, :, 0] >= e[0, :, 1], plan.merge[:, 1], plan.merge[:, 0])
                follower[behind[close]] = True
                plan.merge_sep = np.where(close, distance - 1e-6, plan.merge_sep)
                plan.kernel_arrays = plan.kernel_arrays._replace(merge_sep=np.ascontiguousarray(plan.merge_sep))
        return follower

    def _reach_now(self, plan: _Plan, a_max: float, speed: np.ndarray | None = None) -> np.ndarray:
        """The speeds now as the rules' stopping distances read them (:func:`envs.planners._shield_kernel.reach_speeds`:
        raised by what latency and lag add; the speeds themselves without them)."""
        speed = np.ascontiguousarray(plan.speed if speed is None else speed, dtype=float)
        act = plan.actuation
        if act is None:
            return speed
        return _shield_kernel.reach_speeds(
            speed, act.realised, act.previous, float(a_max), act.lag, act.latency, _STANDING
        )

    # ------------------------------------------------------------------ the fallback
    def _committed_now(self, plan: _Plan, a_max: float) -> np.ndarray:
        """:meth:`committed` in the state now, computed once per plan (three rules of a check read it)."""
        go = plan.committed_now
        if go is None:
            go = plan.committed_now = self.committed(plan, plan.arc, self._reach_now(plan, a_max), a_max)
        return go

    def committed(self, plan: _Plan, arc: np.ndarray, speed: np.ndarray, a_max: float) -> np.ndarray:
        """``(n,)`` bool: the vehicle can no longer stop before its first zone, or has cleared them all (compiled)."""
        arc, speed = np.ascontiguousarray(arc, dtype=float), np.ascontiguousarray(speed, dtype=float)
        return _shield_kernel.committed(plan.kernel_arrays, arc, speed, float(a_max), _STANDING, _STOP_SLACK)

    def _fallback(self, scene: Scene, plan: _Plan, arc: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """The fallback's accelerations in a state: brake, or proceed while keeping a safe gap.

        Compiled, as the prediction.
        """
        a_max = float(scene.a_max)
        speed = np.ascontiguousarray(speed, dtype=float)
        return _shield_kernel.fallback(
            plan.kernel_arrays,
            np.ascontiguousarray(arc, dtype=float),
            speed,
            speed if plan.actuation is None else self._reach_now(plan, a_max, speed),
            a_max,
            float(scene.dt),
            min(self.proceed_acceleration, a_max),
            self.gap_margin,
            _STANDING,
            _STOP_SLACK,
        )

    # ------------------------------------------------------------------ prediction and check
    def substeps(self, scene: Scene) -> int:
        """Sub-steps per period of the prediction: the plant's (``scene.substeps``, e.g. SUMO's 20 Hz plant), else
        :attr:`simulation_frequency`'s. A prediction integrated at another rate than the plant's drifts from it,
        and the plan it accepted no longer holds at the next step."""
        if scene.substeps is not None:
            return max(1, int(scene.substeps))
        return max(1, int(round(self.simulation_frequency * float(scene.dt))))

    def predict(
        self, scene: Scene, plan: _Plan, command: np.ndarray, horizon: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Arcs at every simulation sub-step: ``command`` for one period, then the fallback.

        Compiled (:mod:`envs.planners._shield_kernel`): the periods are sequential and the arrays
        small, so NumPy's per-call overhead made most of the shield's cost.

        :param horizon: longest prediction [s] (default: the shield's ``horizon``)
        :return: ``(T + 1, n)`` arcs (row 0: now) and ``(T + 1, n)`` speeds
        """
        dt = float(scene.dt)
        substeps = self.substeps(scene)
        steps = max(1, int(np.ceil((self.horizon if horizon is None else horizon) / dt - 1e-9)))
        arcs = np.empty((steps * substeps + 1, len(plan.arc)))
        speeds = np.empty_like(arcs)
        arcs[0], speeds[0] = plan.arc, plan.speed
        kernel, head = _shield_kernel.predict, ()
        if plan.actuation is not None:  # latency and lag (`_actuation`)
            kernel, head = _shield_kernel.predict_lagged, (plan.actuation,)
        rows = kernel(
            plan.kernel_arrays,
            envelope_table(scene.layout, self.governor_deceleration),
            *head,
            np.ascontiguousarray(command, dtype=float),
            arcs,
            speeds,
            steps,
            substeps,
            dt / substeps,
            self.max_speed,
            float(scene.a_max),
            dt,
            min(self.proceed_acceleration, float(scene.a_max)),
            self.gap_margin,
            _STANDING,
            _STOP_SLACK,
        )
        return arcs[:rows], speeds[:rows]

    def _conflicts(
        self, scene: Scene, plan: _Plan, arc: np.ndarray, speed: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The conflicts of a prediction (compiled).

        :param arc: ``(T + 1, n)`` predicted arcs (row 0: now), as :meth:`predict` returns them
        :param speed: ``(T + 1, n)`` predicted speeds
        :return: ``(k,)`` follow pairs whose gap closes, ``(c,)`` crossing pairs in their zone at once,
            ``(g,)`` merging pairs too close after the merge (all bool, at any predicted sub-step), and
            ``(n,)`` bool: vehicles that at the end neither stand before their zones nor have cleared them
        """
        return _shield_kernel.conflicts(plan.kernel_arrays, arc, speed[-1], float(scene.a_max), _STANDING, _STOP_SLACK)

    def _blame(
        self, scene: Scene, plan: _Plan, command: np.ndarray, free: np.ndarray, horizon: float | None = None
    ) -> np.ndarray | None:
        """Vehicles to override so that the plan gets through, ``None`` if it passes as it is.

        A conflict is blamed on a vehicle whose command still differs from the fallback
        (``free``); when both of a pair's do, on the one that comes second: the follower, or the
        later to enter the zone.

        :param horizon: longest prediction [s] (default: the shield's ``horizon``)
        :return: ``(n,)`` bool (all ``False``: conflicts that no free vehicle explains), or ``None``
        """
        arc, speed = self.predict(scene, plan, command, horizon)
        bad_follow, bad_cross, bad_merge, stuck = self._conflicts(scene, plan, arc, speed)
        stuck = stuck & ~plan.human
        if plan.waiting.any():  # predicted standing for good, a waiting human holds who stands behind it, until it goes
            stuck &= speed[-1] > _STANDING
        if plan.human_pair.size:  # an automated vehicle in a going human's zone within the human's window
            bad_human = self._in_human_windows(scene, plan, arc)
            if bad_human.any():  # the automated one is to blame (when its command can still change)
                rows = plan.cross[plan.human_pair[bad_human], 1 - plan.human_col[bad_human]]
                bad_cross = bad_cross.copy()
                bad_cross[plan.human_pair[bad_human][free[rows]]] = True
        conflict = bad_follow.any() or bad_cross.any() or bad_merge.any()
        self._stuck_only = not conflict and stuck.any()
        if not (conflict or stuck.any()):
            return None
        # Compiled (`_shield_kernel.blame`): a few NumPy calls per conflict kind cost more than the whole loop
        return _shield_kernel.blame(
            plan.kernel_arrays, arc, speed[-1], np.ascontiguousarray(plan.arc, dtype=float),
            np.ascontiguousarray(plan.rank, dtype=_INT), np.ascontiguousarray(free, dtype=bool), bad_follow,
            bad_cross, bad_merge, np.ascontiguousarray(stuck, dtype=bool), float(scene.a_max), _STANDING, _STOP_SLACK,
        )  # fmt: skip


def _follow_until(layout, route: np.ndarray, length: np.ndarray, follow: np.ndarray) -> np.ndarray:
    """``(k,)`` the arc of each pair's vehicle ahead at which the pair ends: for one on another route from the
    same spawn lane, where its rear passes the point from which the centre lines part (the simulation then drops
    it as a leader, and the prediction must too: a follower freed within the horizon goes on faster); inf
    for every other pair."""
    follower, ahead = follow[:, 0], follow[:, 1]
    part = parting_arcs(layout)[route[ahead], route[follower]]
    return np.where(np.isfinite(part), part + 0.5 * np.asarray(length, float)[ahead], np.inf)


_MERGING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _merging_routes(layout) -> np.ndarray:
    """``(R, R)`` bool: conflicting routes that end on the same exit lane (merge rather than cross)."""
    if layout not in _MERGING:
        ids = layout.route_lane_ids
        last = ids[np.arange(ids.shape[0]), (ids >= 0).sum(axis=1) - 1]
        _MERGING[layout] = layout.conflicts & (last[:, None] == last[None, :])
    return _MERGING[layout]


_ENVELOPES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def envelope_table(layout, deceleration: float) -> _shield_kernel.EnvelopeTable:
    """The governor's speed envelope of a layout as the compiled prediction reads it (cached).

    ``integrate`` asks the layout for the envelope six times per policy period; the kernel reads
    it from these flat tables instead (the squared envelope, its differences to the next sample and
    the limits, by flat index), with exactly :meth:`envs.simulation.layouts.Layout.envelope_at`'s arithmetic,
    so the prediction stays bitwise the simulation's (``tests/test_shield.py`` checks it).

    :param layout: the intersection
    :param deceleration: the simulation's governor deceleration [m/s^2]
    """
    tables = _ENVELOPES.setdefault(layout, {})
    key = float(deceleration)
    if key not in tables:
        sq = layout.speed_envelope(key) ** 2
        dsq = np.concatenate([sq[:, 1:] - sq[:, :-1], np.zeros((sq.shape[0], 1))], axis=1)
        limit = np.ascontiguousarray(layout.speed_limit, dtype=float).ravel()
        tables[key] = _shield_kernel.EnvelopeTable(
            sq.ravel(), dsq.ravel(), limit, int(sq.shape[1]), int(sq.shape[1] - 1), float(layout.ds)
        )
    return tables[key]


class _Proposal:
    """Stands for the policy inside the training shield, which checks proposals with ``Shield.check``."""

    name = "policy"

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, scene: Scene) -> np.ndarray:
        raise RuntimeError("the training shield checks the policy's proposals; it asks no planner")


def training_shield(simulation_frequency: float, max_speed: float, governor_deceleration: float) -> Shield:
    """The shield of training with ``shield`` (:mod:`envs.simulation.hooks`): it checks the policy's
    proposals with :meth:`Shield.check` and asks no planner.

    :param simulation_frequency: the environment's ``simulation_frequency`` [Hz]
    :param max_speed: its ``max_speed`` [m/s]
    :param governor_deceleration: its ``governor_deceleration`` [m/s^2]
    """
    return Shield(
        _Proposal(),
        simulation_frequency=simulation_frequency,
        max_speed=max_speed,
        governor_deceleration=governor_deceleration,
    )
