"""Arrival-time planning behind the shield (``glide``): full throttle, except where a vehicle's slot says slow down.

Every vehicle drives at full throttle, and the safety shield (:mod:`envs.planners.shield`) keeps
the result collision-free. Full throttle alone makes vehicles race to the line and stop there when
a crossing vehicle holds the junction; ``glide`` instead times their arrival. It reuses the
reservations of :class:`~envs.planners.aim.AIMPlanner` (candidate plans per vehicle, an order,
windows per conflict zone), with three changes:

- **Tight reservations**: the plans accelerate at ``accel`` = 5 m/s^2 with no time ``buffer`` and
  ``follow_headway`` = 1.0 s at the line, since the shield, not the plan's margins, keeps safety.
- **Platoons kept together**: the order is first come, first served by the earliest feasible
  arrival, as AIM's, but a vehicle first seen within ``platoon_gap`` seconds of its leader's arrival
  takes its place right behind the leader, so a same-lane platoon crosses as one and the junction
  switches direction less often.
- **Advice only where it pays, and nothing but the plan**: a vehicle follows its plan's first phase
  only within ``window`` metres of its line and only when its plan would slow or stop it; everyone
  else goes at full throttle. A slowed plan brakes at most ``decel`` towards its cruise speed (never
  below ``floor``) and speeds up at full throttle once its line speed calls for it (AIM's rule); a
  stop plan brakes with IDM towards its line and goes at full throttle there once its start time has
  come. There is no car following and no zone guard on top: the shield keeps every gap, and adding
  both again duplicates it and costs flow and delay (``control="first_phase"``, the default).

``control="guarded"`` is glide as it was first shipped: the plan's command capped by IDM car following
and AIM's zone guard (:meth:`~envs.planners.aim.AIMPlanner.control`), every advised command floored at
``floor`` and no cruise speed below it. ``make_planner("glide")`` without the shield builds that one
(:data:`GUARDED`), since there nothing else keeps a gap; ``glide+shield`` runs the first-phase control.
Glide is a planner for behind the shield either way: outside its window it drives at full throttle.

**Hysteresis in an imperfect world** (``hysteresis`` [m], 0: off): on a perceived scene (one that carries
``arc_std``, :mod:`envs.simulation.perception`), glide plans each vehicle from a steadied position: the position
it planned from last step, driven on by the perceived speeds, moved towards the perceived one only as far as the
two lie more than ``hysteresis`` apart. A metre of perception error then moves no reservation, and a drifting
bias is followed once it exceeds the band. An exact scene is planned as it is.

The order can be shifted per vehicle (:meth:`GlidePlanner.set_priority`), and the advice window
widened or narrowed per vehicle (:meth:`GlidePlanner.set_windows`): the ``"priority"`` and
``"advice"`` action types of the intersection environments let a policy do so (a zero score drives
exactly as glide).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields

import numpy as np

from envs.planners.aim import AIMParams, AIMPlanner, Reservations
from envs.planners.errors import checked_accelerations
from envs.planners.idm import DEFAULT_IDM, IDMParams, idm_acceleration, leader_chain_max
from envs.simulation.config import GLIDE_VERSION_NAMES
from envs.simulation.scene import Scene

# Added per link of a platoon so that its members keep their order (AIM's own chain offset).
_CHAIN_OFFSET = 1e-3
# How an advised vehicle follows its plan (see the module docstring).
GLIDE_CONTROLS = ("first_phase", "guarded")


@dataclass(frozen=True)
class GlideParams(AIMParams):
    """Free parameters of :class:`GlidePlanner` (defaults: tuned for the first-phase control, see
    ``docs/baselines.md``); AIM's parameters (:class:`~envs.planners.aim.AIMParams`) with tight
    reservations, plus:

    :param window: a vehicle follows its plan only this close to its line [m] (``inf``: on the
        whole approach); farther out it drives at full throttle
    :param floor: the slowest cruise of a slowed approach [m/s]; with ``control="guarded"`` also the
        floor of every advised command, stops included
    :param platoon_gap: a vehicle first seen within this many seconds of its leader's arrival key
        goes right behind its leader in the order [s] (0: AIM's plain first come, first served)
    :param control: ``"first_phase"`` (the plan's first phase alone, for behind the shield) or
        ``"guarded"`` (capped by IDM car following and AIM's zone guard, see the module docstring)
    :param hysteresis: half-width of the band within which a perceived position does not move the position
        glide plans from [m] (see the module docstring; 0: plan from the perceived position itself)
    """

    accel: float = 5.0
    decel: float = 3.829
    commit_decel: float = 3.903
    buffer: float = 0.007
    follow_headway: float = 1.075
    stop_penalty: float = 0.095
    window: float = 37.449
    floor: float = 2.795
    platoon_gap: float = 3.941
    control: str = "first_phase"
    hysteresis: float = 0.0

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if field.name == "control":
                if value not in GLIDE_CONTROLS:
                    raise ValueError(f"glide's control must be one of {list(GLIDE_CONTROLS)}, got {value!r}")
                continue
            ok = (
                isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0 and not math.isnan(value)
            )
            if not ok or (math.isinf(value) and field.name != "window"):
                allowed = "a number >= 0 or inf" if field.name == "window" else "a finite number >= 0"
                raise ValueError(f"glide's {field.name} must be {allowed}, got {value!r}")


#: Glide as first shipped: AIM's control (IDM car following, zone guard) floored at ``floor``, with the
#: values tuned for it. ``make_planner("glide")`` without the shield, and the scheduler of policy files
#: trained over it (their header's ``action`` names no ``glide``).
GUARDED = GlideParams(
    accel=5.0, decel=1.87, commit_decel=3.83, buffer=0.0, follow_headway=0.91, stop_penalty=1.36, window=16.3,
    floor=3.49, platoon_gap=1.28, control="guarded",
)  # fmt: skip
#: Glide's first hand-set values over the first-phase control: advice within 30 m, no cruise below 2 m/s, a
#: follower within 2.5 s of its leader batched behind it, 1.0 s headway at the line, tight plan constants.
#: More stops saved than the tuned values for more delay; the base that ``lookahead`` searches over.
RECIPE = GlideParams(
    accel=5.0, decel=3.0, commit_decel=5.0, buffer=0.0, follow_headway=1.0, stop_penalty=1.9, window=30.0, floor=2.0,
    platoon_gap=2.5,
)  # fmt: skip
#: Glide's parameter sets by name: the ``action``'s ``glide`` key of the environments and of policy files.
GLIDE_VERSIONS: dict[str, GlideParams] = dict(zip(GLIDE_VERSION_NAMES, (GlideParams(), GUARDED, RECIPE)))


def glide_scheduler(version: str = "first_phase", hold: bool = True) -> GlidePlanner:
    """The scheduler of the ``"priority"`` and ``"advice"`` action types.

    :param version: a key of :data:`GLIDE_VERSIONS`
    :param hold: advice once given holds to the line (:class:`GlidePlanner`'s ``hold``)
    :raises ValueError: an unknown version, naming the allowed ones
    """
    if version not in GLIDE_VERSIONS:
        raise ValueError(f"glide version must be one of {list(GLIDE_VERSIONS)}, got {version!r}")
    return GlidePlanner(params=GLIDE_VERSIONS[version], hold=hold)


class GlidePlanner(AIMPlanner):
    """Full throttle behind the shield, with arrival times from tight, platoon-batched reservations.

    Meant to run behind the shield (``glide+shield``): alone it drives at full throttle wherever
    no slot asks it to slow, and relies on the shield for the rest.

    :param name: the name shown in reports
    :param params: free parameters
    :param idm: IDM constants of car following (its ``acc_max`` is replaced by ``params.accel``)
    :param hold: advice once given holds to the line (a window that shrinks later does not release a vehicle);
        ``False``: every vehicle follows the window of this step
    """

    def __init__(
        self, name: str = "Glide", params: GlideParams | None = None, idm: IDMParams = DEFAULT_IDM, hold: bool = True
    ) -> None:
        super().__init__(name, params if params is not None else GlideParams(), idm)
        self._shift: np.ndarray | None = None
        self._windows: np.ndarray | None = None
        self._held = np.zeros(0, dtype=np.int64)
        self.hold = bool(hold)
        self._steady: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None  # ids (sorted), arcs, speeds, time

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self._shift = self._windows = None
        self._held = np.zeros(0, dtype=np.int64)
        self._steady = None

    def adopt(self, other: GlidePlanner) -> None:
        """Take ``other``'s memory (order, commitments, held advice): plan on from where it stands."""
        self._ids, self._keys, self._committed_at = other._ids, other._keys, other._committed_at
        self._held = other._held

    def fork(self) -> GlidePlanner:
        """A plain glide with this one's parameters and memory (order, commitments, held advice), to plan
        ahead in a copy of the world; the arrays are shared, since glide replaces them and never writes in them."""
        twin = GlidePlanner(self.name, self.params, self.idm, self.hold)
        twin.adopt(self)
        return twin

    def set_priority(self, shift: np.ndarray | None) -> None:
        """Shift the order of the next :meth:`act` (then forgotten).

        :param shift: ``(n,)`` seconds added to each vehicle's arrival key (lower goes earlier), one
            per vehicle of the scene that :meth:`act` gets; ``None`` or all zeros: glide's own order
        """
        self._shift = None if shift is None else np.asarray(shift, dtype=float)

    def set_windows(self, windows: np.ndarray | None) -> None:
        """Set each vehicle's advice window for the next :meth:`act` (then forgotten).

        A vehicle that was once within its window stays advised until its line, whatever later windows say.

        :param windows: ``(n,)`` metres, >= 0: a vehicle follows its plan only this close to its line
            (0: never, full throttle); ``None``: ``params.window`` for all (glide's own)
        """
        self._windows = None if windows is None else np.asarray(windows, dtype=float)

    def set_scores(self, kind: str, offsets: np.ndarray) -> None:
        """Apply a scheduling policy's scores, scaled, to the next :meth:`act`.

        :param kind: ``"priority"``: ``offsets`` shift the order (:meth:`set_priority`, seconds);
            ``"advice"``: they move glide's window (:meth:`set_windows` of ``window + offsets``, never below 0 m)
        :param offsets: ``(n,)`` scores times the action's ``scale``
        """
        if kind == "priority":
            self.set_priority(offsets)
        else:
            self.set_windows(self.advice_windows(offsets))

    def advice_windows(self, offsets: np.ndarray) -> np.ndarray:
        """The advice windows of an ``"advice"`` policy's offsets: glide's own window moved by them, never below 0 m.

        :param offsets: ``(n,)`` metres (scores times the action's ``scale``)
        """
        return np.maximum(self.params.window + np.asarray(offsets, dtype=float), 0.0)

    def schedule(self, scene: Scene, kind: str, offsets: np.ndarray) -> np.ndarray:
        """Accelerations for ``scene`` under the scores (:meth:`set_scores`), checked as a planner's
        output (the environment's ``"action"`` types ``"priority"`` and ``"advice"``, :mod:`envs.simulation.hooks`).

        :param scene: the scene now (not modified: :meth:`act` gets a copy)
        :param kind: ``"priority"`` or ``"advice"``
        :param offsets: see :meth:`set_scores`
        :raises envs.planners.errors.PlannerError: an invalid output
        """
        self.set_scores(kind, offsets)
        return checked_accelerations(self.act(scene.copy()), scene, self.name)

    # ------------------------------------------------------------------ order
    def arrival_keys(self, scene: Scene, earliest: np.ndarray, committed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """AIM's remembered keys, with new vehicles batched behind their leaders (see the module docstring)."""
        new = ~np.isin(scene.vehicle_id, self._ids)
        keys, since = super().arrival_keys(scene, earliest, committed)
        gap = self.params.platoon_gap
        leader = scene.leader
        src = np.maximum(leader, 0)
        joins = new & (leader >= 0) & (keys - keys[src] <= gap)
        if not joins.any():
            return keys, since
        out = keys.copy()
        for _ in range(len(out)):  # along the chains, one link per pass (a platoon of k needs k passes)
            batched = np.where(joins, out[src] + _CHAIN_OFFSET, out)
            if np.array_equal(batched, out):
                break
            out = batched
        order = np.argsort(scene.vehicle_id)
        self._keys = out[order]  # remembered as batched: the place is kept on later steps
        return out, since

    def order_keys(self, scene: Scene, keys: np.ndarray) -> np.ndarray:
        """The arrival keys, shifted by :meth:`set_priority` (a follower still never before its leader)."""
        shift, self._shift = self._shift, None
        if shift is None or not shift.any():
            return keys
        if shift.shape != keys.shape:
            raise ValueError(f"glide's priority shift must have one value per vehicle ({keys.size}), got {shift.shape}")
        return leader_chain_max(keys + shift, scene.leader, _CHAIN_OFFSET)

    # ------------------------------------------------------------------ planning
    def _grids(self, top_speed: float) -> tuple[np.ndarray, np.ndarray]:
        """AIM's grids; with ``control="guarded"`` without the cruise speeds below ``floor``."""
        u, waits = super()._grids(top_speed)
        if self.params.control == "guarded":
            u = u[u >= self.params.floor - 1e-9]
        return u, waits

    # ------------------------------------------------------------------ control
    def advice_window(self, scene: Scene) -> float | np.ndarray:
        """How close to its line a vehicle follows its plan [m]: :meth:`set_windows`' windows, else
        ``params.window`` (a subclass may set one per vehicle, an ``(n,)`` array)."""
        if self._windows is None:
            return self.params.window
        if self._windows.shape != (scene.num_vehicles,):
            raise ValueError(
                f"glide's advice windows must have one value per vehicle ({scene.num_vehicles}), "
                f"got {self._windows.shape}"
            )
        return self._windows

    def steadied(self, scene: Scene) -> Scene:
        """The scene glide plans from: with ``hysteresis`` on a perceived scene, each vehicle moved to its steadied
        position (see the module docstring; the distances and gaps shifted with it); else ``scene`` itself.

        :param scene: the scene now (not modified)
        """
        band = self.params.hysteresis
        if band <= 0 or scene.arc_std is None or scene.arc is None:
            self._steady = None
            return scene
        ids, arc, v = scene.vehicle_id, scene.arc, scene.speed
        planned = arc
        if self._steady is not None and self._steady[0].size:
            before, arc0, v0, t0 = self._steady
            pos = np.minimum(np.searchsorted(before, ids), before.size - 1)
            known = before[pos] == ids
            driven = arc0[pos] + 0.5 * (v0[pos] + v) * (scene.time - t0)
            # where the perceived lies within the band around the driven position, the driven; else the nearer
            # end of the band around the perceived (moved only by the excess)
            planned = np.where(known, arc - np.clip(arc - driven, -band, band), arc)
        order = np.argsort(ids)
        self._steady = (ids[order], planned[order], v[order], float(scene.time))
        shift = planned - arc
        if not shift.any():
            return scene
        leader = scene.leader
        ahead = np.where(leader >= 0, shift[np.maximum(leader, 0)], 0.0)
        return dataclasses.replace(
            scene, arc=planned, s=scene.s + shift, dist_to_entry=scene.dist_to_entry - shift,
            dist_to_exit=scene.dist_to_exit - shift, gap=np.where(leader >= 0, scene.gap + ahead - shift, scene.gap),
        )  # fmt: skip

    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles == 0:
            self._shift = self._windows = None
            return np.zeros(0)
        scene = self.steadied(scene)
        plan = self.reserve(scene)
        guarded = self.params.control == "guarded"
        planned = self.control(scene, plan) if guarded else self.first_phase(scene, plan)
        dist = scene.dist_to_entry
        slowed = plan.kind[plan.choice] != 0
        window, self._windows = self.advice_window(scene), None
        # Advice once given holds to the line: a window that shrinks between steps (a policy's) must not
        # switch a vehicle between its slot's slow approach and full throttle. A fixed window changes
        # nothing (a vehicle's distance to its line never grows).
        within = (dist > 0) & (dist <= window)
        if self.hold:
            within |= (dist > 0) & np.isin(scene.vehicle_id, self._held)
        self._held = scene.vehicle_id[within]
        advised = slowed & within & (scene.dist_to_exit > 0)
        if guarded:  # never brake below the floor, nor hold a slower vehicle: a stop, if needed, is the shield's
            planned = np.maximum(
                planned, np.clip((self.params.floor - scene.speed) / scene.dt, scene.a_min, scene.a_max)
            )
        return np.where(advised, planned, scene.a_max)

    def first_phase(self, scene: Scene, plan: Reservations) -> np.ndarray:
        """Each vehicle's command to follow the first phase of its reservation and nothing else (no car
        following, no zone guard: the shield keeps the gaps).

        :param scene: the vehicles now
        :param plan: the reservations of this step (:meth:`reserve`)
        :return: ``(n,)`` accelerations within the scene's bounds (meant for the advised vehicles)
        """
        p = self.params
        n = scene.num_vehicles
        rows = np.arange(n)
        kind, u = plan.kind[plan.choice], plan.cruise[plan.choice]
        v, dist, dt = scene.speed, scene.dist_to_entry, scene.dt
        # Slowed approach: towards its cruise speed (not below the floor), at full throttle once the line speed calls.
        w = plan.line_speed[rows, plan.choice]
        speed_up = (w > v) & (dist <= (w**2 - v**2) / (2.0 * p.accel) + v * dt)
        cruise = np.maximum(np.where(np.isnan(u), 0.0, u), p.floor)
        slowed = np.where(speed_up, scene.a_max, np.clip((cruise - v) / dt, -p.decel, p.accel))
        # Stop: IDM towards the line, full throttle there once the start time has come.
        at_line = (plan.rest <= 0.0) & (plan.start[rows, plan.choice] <= 1e-9)
        to_stop = np.maximum(dist, 0.0) + self.idm.jam_distance
        target = np.where(dist <= 0.5, 0.0, scene.speed_limit)
        stop = np.where(at_line, scene.a_max, idm_acceleration(v, target, to_stop, np.zeros(n), dt, self.idm))
        return np.clip(np.where(kind == 1, slowed, stop), scene.a_min, scene.a_max)
