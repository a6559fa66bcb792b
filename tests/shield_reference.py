"""The shield's rules in NumPy: the oracle that the compiled kernels (``envs/planners/_shield_kernel.py``,
the only implementation the shield runs) match bit for bit.

:func:`plan_pairs_numpy` builds the pairs of ``Shield._plan`` (compiled: ``_shield_kernel.pairs``);
:func:`fallback_numpy`, :func:`predict_numpy`, :func:`conflicts_numpy` and :func:`blame_numpy` compute what
``Shield._fallback``, ``Shield.predict``, ``Shield._conflicts`` and ``Shield._blame`` compute, from the same plan
(``Shield._plan``): the prediction with :func:`envs.simulation.engine.integrate` itself, on a NumPy view
(:class:`PredictionLayout`) of the speed-envelope tables that the kernels read. The helpers below
(:func:`committed`, :func:`waits`, :func:`leaders_now`, ...) are the rules the kernels implement
once for the shield and the fallback. A change to a rule is made in the kernel; these functions
change with it only if the test that compares them says that the rule, not a rounding, changed.
"""

from __future__ import annotations

import weakref

import numpy as np

from envs.planners import _shield_kernel
from envs.planners.shield import _STANDING, _STOP_SLACK, Shield, _merging_routes, _Plan, envelope_table
from envs.simulation.engine import integrate
from envs.simulation.layouts import parting_arcs
from envs.simulation.scene import Scene


def can_stop_before(arc: np.ndarray, speed: np.ndarray, line: np.ndarray, a_max: float) -> np.ndarray:
    """Whether braking at ``a_max`` stops a vehicle's centre at or before ``line`` (elementwise).

    A standing vehicle outside the line can always wait (the slack is for moving ones only).
    """
    return (arc <= line) & ((speed <= _STANDING) | (arc + speed**2 / (2 * a_max) + _STOP_SLACK <= line))


def plan_pairs_numpy(shield: Shield, scene: Scene, plan: _Plan) -> dict[str, np.ndarray]:
    """The pairs of ``Shield._plan`` and what it derives from them (the fields of :class:`_Plan` that
    ``_shield_kernel.pairs`` returns), from the scene and the plan's hulls.

    :return: field name -> array
    """
    lay, route, length = scene.layout, scene.route, scene.length
    arc, speed, hull_start = plan.arc, plan.speed, plan.hull_start
    # Same path: the leader and the leader's leader; the next vehicle ahead on the same route; a
    # vehicle ahead on another route from the same spawn lane until the centre lines part.
    lead = scene.leader
    rows = np.flatnonzero(lead >= 0)
    second = rows[lead[lead[rows]] >= 0]
    far = route[lead[lead[second]]]  # the leader's leader's route: on the follower's path (`on_path`)?
    mine = route[second]
    on_path = (mine == far) | (parting_arcs(lay)[far, mine] > -np.inf) | _merging_routes(lay)[mine, far]
    second = second[on_path]
    by_route = np.lexsort((arc, route))
    same = route[by_route[:-1]] == route[by_route[1:]]
    behind, ahead = by_route[:-1][same], by_route[1:][same]
    span = arc[None, :] - arc[:, None] - (length[:, None] + length[None, :]) / 2  # [behind, ahead]
    d_behind, d_ahead = np.nonzero(
        (span > 0) & (arc[None, :] - length[None, :] / 2 < parting_arcs(lay)[route[None, :], route[:, None]])
    )
    behind, ahead = np.concatenate([behind, d_behind]), np.concatenate([ahead, d_ahead])
    follow = np.stack(
        [np.concatenate([rows, second, behind]), np.concatenate([lead[rows], lead[lead[second]], ahead])], axis=1
    ).astype(np.int64)
    follow_gap = np.concatenate(
        [
            scene.gap[rows],
            scene.gap[second] + length[lead[second]] + scene.gap[lead[second]],
            arc[ahead] - arc[behind] - (length[ahead] + length[behind]) / 2,
        ]
    )
    if plan.widen is not None:  # declared bounds: a gap may be shorter by both vehicles' widening
        follow_gap = follow_gap - plan.widen[follow[:, 0]] - plan.widen[follow[:, 1]]
    # Conflicting routes, among the vehicles that may commit.
    may = shield._may_commit(scene, arc, speed, hull_start) | plan.waiting  # a waiting human keeps its windows
    rows = np.flatnonzero(may) if shield._prune else np.arange(len(arc))
    i, j = np.nonzero(lay.conflicts[route[rows, None], route[None, rows]])
    i, j = rows[i[i < j]], rows[j[i < j]]
    is_merge = _merging_routes(lay)[route[i], route[j]]
    pairs = np.stack([i, j], axis=1).astype(np.int64)
    cross, merge = pairs[~is_merge], pairs[is_merge]
    r = route[cross]
    half = length[cross] / 2
    pad = plan.pad[cross]  # each vehicle's zone padding (0 for a waiting human)
    cross_lo = lay.zone_start[r, r[:, ::-1]] - pad - half
    cross_hi = lay.zone_end[r, r[:, ::-1]] + pad + half
    if shield._prune:
        ahead = (arc[cross] < cross_hi).all(axis=1)
        cross, cross_lo, cross_hi = cross[ahead], cross_lo[ahead], cross_hi[ahead]
    r = route[merge]
    order = np.lexsort((scene.vehicle_id, hull_start - arc))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    x0 = arc[cross]
    less = less_far_through(x0, cross_lo, cross_hi, np.asarray(scene.vehicle_id)[cross])
    back = less[:, 1].astype(np.int64)
    pair = np.arange(len(back))
    return {
        "follow": follow,
        "follow_gap": follow_gap,
        "cross": cross,
        "cross_lo": cross_lo,
        "cross_hi": cross_hi,
        "cross_already": ((x0 > cross_lo) & (x0 < cross_hi)).all(axis=1) & (speed[cross[pair, back]] <= _STANDING),
        "cross_back": back,
        "cross_stop": x0[pair, back] + _STOP_SLACK,
        "merge": merge,
        "merge_lo": lay.zone_start[r, r[:, ::-1]] - plan.pad[merge] - length[merge] / 2,
        "merge_exit": lay.exit_arc[r],
        "merge_sep": length[merge].sum(axis=1) / 2 + shield.merge_margin
        if plan.widen is None
        else length[merge].sum(axis=1) / 2 + shield.merge_margin + plan.widen[merge[:, 0]] + plan.widen[merge[:, 1]],
        "rank": rank,
    }


def less_far_through(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``(c, 2)`` bool over crossing pairs: this side is less far through the pair's zone than the
    other (ties: the higher id), the one to hold when both are in it."""
    through = (x - lo) / (hi - lo)
    return (through < through[:, ::-1]) | ((through == through[:, ::-1]) & (ids > ids[:, ::-1]))


def committed(plan: _Plan, arc: np.ndarray, speed: np.ndarray, a_max: float) -> np.ndarray:
    """``(n,)`` bool: the vehicle can no longer stop before its first zone, or has cleared them all."""
    return ~can_stop_before(arc, speed, plan.hull_start, a_max) | (arc > plan.hull_end)


def settled(plan: _Plan, arc: np.ndarray, speed: np.ndarray, a_max: float) -> np.ndarray:
    """``(n,)`` bool: the vehicle stands before its zones, or has cleared them."""
    standing = (speed <= _STANDING) & ~committed(plan, arc, speed, a_max)
    return standing | (arc > plan.hull_end)


def waits(plan: _Plan, arc: np.ndarray, speed: np.ndarray, go: np.ndarray, a_max: float) -> np.ndarray:
    """``(c, 2)`` bool over the crossing pairs: this side waits for the other side (a committed vehicle
    that can still stop before the pair's zone, while its partner cannot or is in it and has not
    cleared it; two inside one zone: the one less far through)."""
    x, lo, hi = arc[plan.cross], plan.cross_lo, plan.cross_hi
    can_stop = can_stop_before(x, speed[plan.cross], lo, a_max)
    wait = go[plan.cross] & can_stop & ~can_stop[:, ::-1] & (x[:, ::-1] < hi[:, ::-1])
    both = ((x > lo) & (x < hi)).all(axis=1)
    return wait | (both[:, None] & less_far_through(x, lo, hi, plan.vehicle_id[plan.cross]))


def yielding(plan: _Plan, arc: np.ndarray, speed: np.ndarray, go: np.ndarray, a_max: float) -> np.ndarray:
    """``(n,)`` bool: committed vehicles that the fallback holds for a crossing partner (:func:`waits`)."""
    hold = np.zeros(len(arc), bool)
    if plan.cross.size:
        hold[plan.cross[waits(plan, arc, speed, go, a_max)]] = True
    return hold


def leaders_now(
    shield: Shield, plan: _Plan, arc: np.ndarray, go: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(follower, ahead, bumper gap)`` of every same-path pair, and of every pair on merging paths
    whose vehicle ahead (along the common exit lane) proceeds (``go``) or has reached the merge."""
    f, ahead = plan.follow[:, 0], plan.follow[:, 1]
    gap = plan.follow_gap + (arc[ahead] - plan.arc[ahead]) - (arc[f] - plan.arc[f])
    live = arc[ahead] < plan.follow_until  # the others' vehicle ahead has turned off: no gap to keep
    f, ahead, gap = f[live], ahead[live], gap[live]
    if plan.merge.size:
        m0, m1 = plan.merge[:, 0], plan.merge[:, 1]
        a0, a1 = arc[m0], arc[m1]
        e0, e1 = a0 - plan.merge_exit[:, 0], a1 - plan.merge_exit[:, 1]
        second = e0 >= e1  # vehicle 1 is behind along the common exit lane
        first = np.where(second, m0, m1)
        active = np.where(second, a0 > plan.merge_lo[:, 0], a1 > plan.merge_lo[:, 1]) | go[first]
        mf, ma = np.where(second, m1, m0)[active], first[active]
        # kept at gap_margin by the fallback: half a gap margin more than the check's distance
        mgap = (np.abs(e0 - e1) - plan.merge_sep + 0.5 * shield.gap_margin)[active]
        f, ahead, gap = np.concatenate([f, mf]), np.concatenate([ahead, ma]), np.concatenate([gap, mgap])
    return f, ahead, gap


def gaps_hold(
    shield: Shield, plan: _Plan, arc: np.ndarray, speed: np.ndarray, go: np.ndarray, a_max: float, reach=None
) -> bool:
    """Every leader relation of :func:`leaders_now` (a merging one only where the follower yields) keeps the
    check's floor: now, and once both have stopped at ``a_max`` when the follower is the faster (with the
    stopping slack); the check's floor of a merging pair is a distance of 0, half a gap margin below its gap."""
    f, ahead, gap = leaders_now(shield, plan, arc, go)
    live = plan.follow_floor[arc[plan.follow[:, 1]] < plan.follow_until]
    floor = np.concatenate([live, np.full(len(f) - len(live), 0.5 * shield.gap_margin)])
    yields = np.concatenate([np.ones(len(live), bool), ~np.asarray(plan.human, bool)[f[len(live) :]]])
    vf, va = (speed if reach is None else reach)[f], speed[ahead]
    stop = gap - (vf**2 - va**2) / (2 * a_max)
    room = (gap >= floor) & ((vf <= va) | (stop >= floor + _STOP_SLACK))
    return bool((room | ~yields).all())


def travel(speed: np.ndarray, acc: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance and end speed after ``dt`` at constant ``acc``, stopping at 0."""
    end = speed + acc * dt
    to_stop = speed**2 / (2 * max(-acc, 1e-12))
    return np.where(end < 0, to_stop, 0.5 * (speed + end) * dt), np.maximum(end, 0.0)


def safe_gap_after(
    gap: np.ndarray, v_follower: np.ndarray, v_ahead: np.ndarray, acc: float, a_max: float, dt: float, margin: float
) -> np.ndarray:
    """Whether after ``dt`` at ``acc`` the follower can still stop behind a vehicle that brakes at
    ``a_max`` now (responsibility-sensitive safety with equal braking)."""
    travel_f, v_f = travel(v_follower, acc, dt)
    travel_a, v_a = travel(v_ahead, -a_max, dt)
    after = gap + travel_a - travel_f
    return after - np.maximum(v_f**2 - v_a**2, 0.0) / (2 * a_max) >= margin


def shield_keep(plan: _Plan, arc: np.ndarray, go: np.ndarray) -> np.ndarray:
    """The room the fallback keeps over the gap margin in the active merging pairs (:func:`leaders_now`'s order)."""
    if not plan.merge.size:
        return np.zeros(0)
    m0, m1 = plan.merge[:, 0], plan.merge[:, 1]
    e0, e1 = arc[m0] - plan.merge_exit[:, 0], arc[m1] - plan.merge_exit[:, 1]
    second = e0 >= e1
    first = np.where(second, m0, m1)
    active = np.where(second, arc[m0] > plan.merge_lo[:, 0], arc[m1] > plan.merge_lo[:, 1]) | go[first]
    return plan.kernel_arrays.merge_keep[active]


def fallback_given(
    shield: Shield,
    plan: _Plan,
    arc: np.ndarray,
    speed: np.ndarray,
    go: np.ndarray,
    a_max: float,
    dt: float,
    reach: np.ndarray | None = None,
) -> np.ndarray:
    """The fallback's accelerations in a state, with the committed vehicles (``go``) known; ``reach``: the speeds
    that stopping distances read under latency and lag (:func:`reach_speeds`; default the speeds)."""
    reach = speed if reach is None else reach
    proceed = min(shield.proceed_acceleration, a_max)
    acc = np.where(go & ~yielding(plan, arc, reach, go, a_max), proceed, -a_max)
    f, ahead, gap = leaders_now(shield, plan, arc, go)
    if plan.follow_keep is not None:  # the room kept over the gap margin on a perceived scene (follow pairs first)
        live = plan.follow_keep[arc[plan.follow[:, 1]] < plan.follow_until]
        gap = np.concatenate([gap[: len(live)] - live, gap[len(live) :] - shield_keep(plan, arc, go)])
    if f.size:
        ok = safe_gap_after(gap, reach[f], speed[ahead], proceed, a_max, dt, shield.gap_margin)
        # a human driver keeps no gap to a merging vehicle (its model sees it once it leads on the lane)
        live = int((arc[plan.follow[:, 1]] < plan.follow_until).sum())  # the follow pairs come first
        ok |= (np.arange(f.size) >= live) & np.asarray(plan.human, bool)[f]
        acc[f[~ok & go[f]]] = min(proceed, -a_max)
    return acc


def fallback_numpy(shield: Shield, scene: Scene, plan: _Plan, arc: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """``Shield._fallback``: brake, or proceed while keeping a safe gap (the state now: its reach speeds)."""
    a_max = float(scene.a_max)
    act = plan.actuation
    reach = speed if act is None else reach_speeds(speed, act, a_max)
    go = committed(plan, arc, reach, a_max)
    return fallback_given(shield, plan, arc, speed, go, a_max, float(scene.dt), reach)


def reach_speeds(
    speed: np.ndarray, act, a_max: float, r: np.ndarray | None = None, previous=None, margin: float = 0.0
) -> np.ndarray:
    """The kernels' reach speeds (``_shield_kernel.reach_speeds``, a primitive that the oracle shares, as it shares
    ``can_stop``; ``tests/test_shield_declared.py`` checks it against the plant's actuator)."""
    r = act.realised if r is None else r
    previous = act.previous if previous is None else previous
    return _shield_kernel.reach_speeds(
        np.ascontiguousarray(speed, dtype=float), np.ascontiguousarray(r, dtype=float),
        np.ascontiguousarray(previous, dtype=float), a_max, act.lag, act.latency, _STANDING, margin,
    )  # fmt: skip


def actuate(act, command: np.ndarray, speed: np.ndarray, r: np.ndarray, previous: np.ndarray) -> tuple:
    """One period of :class:`envs.simulation.faults.Actuator` (its arithmetic): ``(S, n)`` mean accelerations per
    sub-step and the realised accelerations at the period's end."""
    commanded = act.old_share[:, None] * previous[None, :] + (1.0 - act.old_share)[:, None] * command[None, :]
    r = np.where(speed <= 0.0, np.maximum(r, 0.0), r)
    out = np.empty_like(commanded)
    for k in range(commanded.shape[0]):
        out[k] = commanded[k] + (r - commanded[k]) * act.mean_share
        r = commanded[k] + (r - commanded[k]) * act.decay
    return out, r


def predict_numpy(shield: Shield, scene: Scene, plan: _Plan, command: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Shield.predict``: ``command`` for one period, then the fallback, with :func:`envs.simulation.engine.integrate`.

    :return: ``(T + 1, n)`` arcs (row 0: now) and ``(T + 1, n)`` speeds
    """
    dt = float(scene.dt)
    substeps = max(1, int(round(shield.simulation_frequency * dt)))
    h = dt / substeps
    steps = max(1, int(np.ceil(shield.horizon / dt - 1e-9)))
    arcs, speeds = [plan.arc[None]], [plan.speed[None]]
    arc, speed, acc = plan.arc, plan.speed, command
    a_max = float(scene.a_max)
    b = shield.governor_deceleration
    view = prediction_layout(scene.layout, b)
    act = plan.actuation
    if act is not None:
        r, previous = act.realised.copy(), act.previous.copy()
    for _ in range(steps):
        if act is not None:  # latency and lag: each period through the actuator, the rules on the reach speeds
            sub, r = actuate(act, acc, speed, r, previous)
            previous = np.asarray(acc, float).copy()
            v, x, _ = integrate(view, plan.route, arc, speed, sub, substeps, h, shield.max_speed, b)
            arcs.append(x[1:])
            speeds.append(v[1:])
            arc, speed = x[-1], v[-1]
            reach = reach_speeds(speed, act, a_max, r, previous, act.margin)
            go = committed(plan, arc, reach, a_max)
            settled_now = (((reach <= _STANDING) & ~go) | (arc > plan.hull_end)).all()
            if settled_now and gaps_hold(shield, plan, arc, speed, go, a_max, reach):
                break
            acc = fallback_given(shield, plan, arc, speed, go, a_max, dt, reach)
            continue
        v, x, _ = integrate(view, plan.route, arc, speed, acc, substeps, h, shield.max_speed, b)
        arcs.append(x[1:])
        speeds.append(v[1:])
        arc, speed = x[-1], v[-1]
        go = committed(plan, arc, speed, a_max)
        settled_now = (((speed <= _STANDING) & ~go) | (arc > plan.hull_end)).all()  # `settled`, sharing `go`
        if settled_now and gaps_hold(shield, plan, arc, speed, go, a_max):
            break  # everyone stands before its zones or has left them, with room behind: the fallback keeps it so
        acc = fallback_given(shield, plan, arc, speed, go, a_max, dt)
    return np.concatenate(arcs), np.concatenate(speeds)


def conflicts_numpy(
    shield: Shield, scene: Scene, plan: _Plan, arc: np.ndarray, speed: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``Shield._conflicts``: follow pairs whose gap closes, crossing pairs in their zone at once,
    merging pairs too close after the merge, and vehicles that end neither settled nor cleared."""
    del shield  # the check reads the plan only
    later = arc[1:]
    # Same path and merged: the gap to the vehicle ahead must stay open.
    f, ahead = plan.follow[:, 0], plan.follow[:, 1]
    gap = plan.follow_gap + (later[:, ahead] - plan.arc[ahead]) - (later[:, f] - plan.arc[f])
    gap = np.where(later[:, ahead] < plan.follow_until, gap, np.inf)
    bad_follow = (gap < plan.follow_floor).any(axis=0)
    # Crossing: never both in the pair's zone.
    x = later[:, plan.cross]  # (T, c, 2)
    both = ((x > plan.cross_lo) & (x < plan.cross_hi)).all(axis=2)
    if plan.cross_already.any():
        moved = x[:, np.arange(len(plan.cross)), plan.cross_back] > plan.cross_stop
        both = np.where(plan.cross_already, both & moved, both)
    bad_cross = both.any(axis=0)
    # Merging: a separation along the common exit lane once both have reached the merge.
    x = later[:, plan.merge]
    reached = (x > plan.merge_lo).all(axis=2)
    e = x - plan.merge_exit
    bad_merge = (reached & (np.abs(e[..., 0] - e[..., 1]) < plan.merge_sep)).any(axis=0)
    # At the end, everyone stands before its zones or has cleared them.
    stuck = ~settled(plan, arc[-1], speed[-1], scene.a_max)
    return bad_follow, bad_cross, bad_merge, stuck


class PredictionLayout:
    """The layout as :func:`envs.simulation.engine.integrate` sees it in :func:`predict_numpy`: the governor's
    speed envelope read in NumPy from the tables that the compiled prediction reads
    (:func:`envs.planners.shield.envelope_table`), with :meth:`envs.simulation.layouts.Layout.envelope_at`'s
    arithmetic. Every other attribute is the layout's.

    :param layout: the intersection
    :param deceleration: the governor deceleration the tables are built for [m/s^2]
    """

    def __init__(self, layout, deceleration: float) -> None:
        self.layout = weakref.proxy(layout)  # the cache below is keyed weakly by the layout
        self.deceleration = float(deceleration)
        self.table = envelope_table(layout, self.deceleration)

    def envelope_at(self, route: np.ndarray, arc: np.ndarray, deceleration: float) -> np.ndarray:
        if float(deceleration) != self.deceleration:
            return self.layout.envelope_at(route, arc, deceleration)
        # Layout.envelope_at: u, i0, f as there; the limit's sample int(arc / ds) clipped to
        # [0, last] is i0, or last where u reached it.
        t = self.table
        u = np.minimum(np.maximum(arc / t.ds, 0.0), t.last)
        i0 = np.minimum(u.astype(np.int64), t.last - 1)
        f = u - i0
        flat = route * t.columns + i0
        envelope = np.sqrt(t.sq.take(flat) + t.dsq.take(flat) * f)
        return np.minimum(envelope, t.limit.take(flat + (u >= t.last)))

    def __getattr__(self, name: str):
        return getattr(self.layout, name)


_VIEWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _blame_pairs(blamed: np.ndarray, free: np.ndarray, second: np.ndarray, first: np.ndarray) -> None:
    """Mark, per conflicting pair, the free one; ``second`` if both are free (in place)."""
    pick = np.where(free[second], second, first)
    blamed[pick[free[pick]]] = True


def blame_numpy(
    shield: Shield,
    scene: Scene,
    plan: _Plan,
    arc: np.ndarray,
    speed: np.ndarray,
    free: np.ndarray,
    bad_follow: np.ndarray,
    bad_cross: np.ndarray,
    bad_merge: np.ndarray,
    stuck: np.ndarray,
) -> np.ndarray:
    """Who ``Shield._blame`` overrides for the conflicts of a prediction (``_shield_kernel.blame``): a conflict is
    blamed on a free vehicle; when both of a pair are free, on the one that comes second (the follower, the
    later to enter the zone, the one behind after a merge); stuck free vehicles but the first in order, and the
    free vehicle ahead of a stuck committed one.

    :param arc: ``(T + 1, n)`` predicted arcs, ``speed`` the speeds (as ``Shield.predict`` returns them)
    :return: ``(n,)`` bool
    """
    later = arc[1:]
    blamed = np.zeros(scene.num_vehicles, bool)
    if bad_follow.any():
        _blame_pairs(blamed, free, plan.follow[bad_follow, 0], plan.follow[bad_follow, 1])
    if bad_cross.any():
        entered = later > plan.hull_start
        t_in = np.where(entered.any(axis=0), entered.argmax(axis=0), len(later))
        key = t_in * (len(plan.rank) + 1) + plan.rank
        pairs = plan.cross[bad_cross]
        second = (key[pairs[:, 1]] > key[pairs[:, 0]]).astype(np.int64)
        rows = np.arange(len(pairs))
        _blame_pairs(blamed, free, pairs[rows, second], pairs[rows, 1 - second])
    if bad_merge.any():
        e0 = plan.arc[plan.merge[bad_merge]] - plan.merge_exit[bad_merge]
        back = (e0[:, 0] >= e0[:, 1]).astype(np.int64)
        rows = np.arange(len(back))
        pairs = plan.merge[bad_merge]
        _blame_pairs(blamed, free, pairs[rows, back], pairs[rows, 1 - back])
    if stuck.any():
        stuck_free = stuck & free
        if stuck_free.sum() > 1:
            stuck_free[np.flatnonzero(stuck_free)[np.argmin(plan.rank[stuck_free])]] = False
        blamed |= stuck_free
        go = committed(plan, arc[-1], speed[-1], float(scene.a_max))
        follower, ahead, _ = leaders_now(shield, plan, arc[-1], go)
        culprit = ahead[stuck[follower] & ~free[follower] & free[ahead]]
        blamed[culprit] = True
    return blamed


def prediction_layout(layout, deceleration: float) -> PredictionLayout:
    """The (cached) :class:`PredictionLayout` of a layout and governor deceleration."""
    views = _VIEWS.setdefault(layout, {})
    key = float(deceleration)
    if key not in views:
        views[key] = PredictionLayout(layout, key)
    return views[key]
