"""Simulation, scene and graph building against a plain NumPy lower bound doing the same work.

Per policy step (15 Hz simulation, 5 Hz policy: 3 sub-steps), both sides do:

- collision candidates: poses, leaders (each vehicle's position on every other's route), close
  pairs by centre distance;
- 3 sub-steps of the kinematic update with the speed governor (the braking envelope of the lane
  limits, looked up at the old and new arc);
- the collision check along the sub-step trajectory at the simulation's fine check times: a 1-D
  bumper check for followers on the spawn and exit lanes, the separating-axis test on the close
  pairs near the intersection;
- one graph observation: poses and leaders of the new state, features ``[s, v, d]`` (``d`` from
  all-pairs inverse Mahalanobis distances), same-lane and crossing edges, padded into the
  ``GraphSpace`` arrays.

The bound (:func:`bound_step`) is that work written as one flat NumPy function over precomputed
layout tables, state carried in plain arrays between steps (no objects, no caches, no events).
"Ours" is :class:`envs.simulation.engine.Simulation` (``step``, ``scene``) plus
:func:`envs.simulation.graph.build_observation`, as the environment calls them, and the whole
``env.step`` (adds reward terms, spawning and ``info``). Stock highway-env ``intersection-v0`` is
topped up to the same vehicle counts before every step (see :func:`_time_stock`) and steps IDLE at
its 1 Hz policy with 15 Hz simulation.

The fleet: ``n`` vehicles placed at random on the 4-way layout's routes (seeded), speeds 2-8 m/s,
commands drawn uniformly in ``[-3, 3]`` m/s^2 every step (the same draws for every side), 25 steps
(5 s) per episode so that nobody reaches the end of its route: the count stays ``n``. Random
placement makes overlaps, so collisions are found (and kept: nobody is removed).

Bound, ours and ``env.step`` run the same episodes in turn in one process (:func:`time_sides`:
each episode ``--repeats`` times, the fastest run counts), for ``--seconds`` per vehicle count;
stock runs at least one step and ``--seconds`` / 6. Units: simulated s per wall s (a policy step
is 0.2 simulated s), policy steps per wall s, ms per policy step, and ours / bound (bound's time
over ours: 1 = as fast); with ``--clock cpu``, per CPU second of this process instead.

With ``--baseline DIR`` the simulation of another checkout (``DIR/envs/simulation/engine.py`` and
``layouts.py``, or a flat ``envs/simulation.py`` from before) runs the same episodes too: a before/after
comparison in one process.

Run: ``python benchmarks/bench_sim_bound.py [--seconds 6] [--repeats 3] [--clock cpu] [--no-stock]
[--baseline DIR]``
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.simulation.engine import SPLIT_CLEARANCE, Simulation
from envs.simulation.graph import NODE_FEATURES, NUM_RELATIONS, build_observation, min_mahalanobis
from envs.simulation.layouts import Layout, build_layout, parting_arcs
from sb3_graph.common.spaces import GraphSpace

COUNTS = (10, 20, 50, 100)
EPISODE_STEPS = 25
MAX_NODES, MAX_EDGES = 128, 16384
HZ_SIM, HZ_POLICY = 15, 5
A_MAX, V_MAX, B_GOV, RESOLUTION, S_REF, S_SCALE, D_MAX = 5.0, 20.0, 3.0, 0.1, 25.0, 0.04, 10.0
# The clock of every measurement: wall time, or this process's CPU time (--clock cpu), which other
# work on a shared machine inflates far less (everything here is single-threaded).
CLOCK: list[Callable[[], float]] = [time.perf_counter]


@dataclass
class Tables:
    """Layout arrays the bound reads (precomputed once)."""

    ds: float
    last: int
    xy: np.ndarray
    heading: np.ndarray
    env2: np.ndarray  # squared braking envelope
    limit: np.ndarray
    lane_start: np.ndarray
    lane_starts: np.ndarray
    lane_ids: np.ndarray
    entry: np.ndarray
    exit: np.ndarray
    touch: np.ndarray
    conflicts: np.ndarray
    parting: np.ndarray


def tables(lay: Layout) -> Tables:
    return Tables(
        lay.ds, lay.xy.shape[1] - 1, lay.xy, lay.heading, lay.speed_envelope(B_GOV) ** 2, lay.speed_limit,
        lay.lane_start, lay.route_lane_starts, lay.route_lane_ids, lay.entry_arc, lay.exit_arc,
        lay.touch_arc, lay.conflicts, parting_arcs(lay),
    )  # fmt: skip


def _pose_leaders(t: Tables, route, arc, length):
    """Poses, lane-based leaders and gaps of one state (what the bound carries between steps)."""
    n = arc.shape[0]
    u = np.minimum(np.maximum(arc / t.ds, 0.0), t.last)
    i0 = np.minimum(u.astype(np.int64), t.last - 1)
    f = u - i0
    p0 = t.xy[route, i0]
    pos = p0 + (t.xy[route, i0 + 1] - p0) * f[:, None]
    h0 = t.heading[route, i0]
    hd = (h0 + (t.heading[route, i0 + 1] - h0) * f + np.pi) % (2 * np.pi) - np.pi
    starts = t.lane_starts[route]
    arcs = np.stack([arc, arc - length / 2 - SPLIT_CLEARANCE])  # centre and split-clearance point
    k = (starts[None] <= arcs[..., None]).sum(axis=2) - 1
    lane = t.lane_ids[route, np.maximum(k, 0)]  # (2, n)
    into = arc - t.lane_start[route[None], lane]
    x = t.lane_start[route[:, None], lane[0][None, :]] + into[0][None, :]
    x_back = t.lane_start[route[:, None], lane[1][None, :]] + into[1][None, :]
    overlaps = (arc - length / 2)[None, :] < t.parting[route[None, :], route[:, None]]  # lanes part slowly
    x_back = np.where(np.isnan(x_back) & overlaps, arc[None, :], x_back)
    x = np.where(np.isfinite(x), x, x_back)
    ahead = x - arc[:, None]
    ahead[~(ahead > 0)] = np.inf  # nan and behind
    ahead[np.arange(n), np.arange(n)] = np.inf
    leader = ahead.argmin(axis=1)
    dist = ahead[np.arange(n), leader]
    has = np.isfinite(dist)
    gap = np.where(has, dist - (length + length[leader]) / 2, np.inf)
    return pos, hd, np.where(has, leader, -1), gap


def _envelope(t: Tables, route, arc):
    """The governor's cap: the braking envelope (squared speed interpolated), at most the limit."""
    u = np.minimum(np.maximum(arc / t.ds, 0.0), t.last)
    k = u.astype(np.int64)  # the limit's sample; clipping u first gives the same index
    i0 = np.minimum(k, t.last - 1)
    sq0 = t.env2[route, i0]
    return np.minimum(np.sqrt(sq0 + (t.env2[route, i0 + 1] - sq0) * (u - i0)), t.limit[route, k])


def bound_step(t: Tables, space: GraphSpace, state: list, acc: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """One policy step of the bound; ``state`` = ``[route, arc, speed, length, width, position,
    heading, leader, gap]`` is updated in place (the last four: of the current arcs).

    :return: the padded observation and the ``(k, 2)`` row pairs that touched during the step
    """
    route, arc, speed, length, width, pos, hd, leader, gap = state
    n, h, period = arc.shape[0], 1.0 / HZ_SIM, 1.0 / HZ_POLICY
    acc = np.minimum(np.maximum(acc, -A_MAX), A_MAX)
    exit_, touch = t.exit[route], t.touch[route]
    # Collision candidates.
    travel = np.minimum(speed * period + 0.5 * A_MAX * period**2, V_MAX * period)
    in_area = (arc + length / 2 >= touch - travel - 1.0) & (arc - length / 2 <= exit_ + travel + 1.0)
    follower = np.flatnonzero((leader >= 0) & ~in_area)
    follower = follower[~in_area[leader[follower]]]
    lead = leader[follower]
    reach = 0.5 * np.hypot(length, width) + travel
    d = pos[:, None, :] - pos[None, :, :]
    close = (d[..., 0] ** 2 + d[..., 1] ** 2 <= (reach[:, None] + reach[None, :]) ** 2) & (
        in_area[:, None] | in_area[None, :]
    )
    ci, cj = np.nonzero(np.triu(close, 1))
    # Sub-steps with the governor: the cap at the start of a sub-step is the one at the end of the
    # previous one, unless the governor moved that end.
    v_all, x_all = np.empty((4, n)), np.empty((4, n))
    v_all[0], x_all[0] = speed, arc
    cap = _envelope(t, route, arc)
    for k in range(3):
        v = np.minimum(np.maximum(v_all[k] + acc * h, 0.0), V_MAX)
        x = x_all[k] + 0.5 * (v_all[k] + v) * h
        cap_x = _envelope(t, route, x)
        v_all[k + 1] = np.minimum(v, np.minimum(cap, cap_x))
        x_all[k + 1] = x_all[k] + 0.5 * (v_all[k] + v_all[k + 1]) * h
        moved = x_all[k + 1] != x
        cap = cap_x
        if moved.any():
            cap[moved] = _envelope(t, route[moved], x_all[k + 1][moved])
    # Collision check at the fine times.
    kf = max(1, int(np.ceil(3.0 * np.diff(x_all, axis=0).max(initial=0.0) / RESOLUTION)))
    tt = (np.arange(1, kf + 1) / kf * h)[None, :, None]
    a_sub = (np.diff(v_all, axis=0) / h)[:, None, :]
    fine = (x_all[:-1, None, :] + v_all[:-1, None, :] * tt + 0.5 * a_sub * tt**2).reshape(-1, n)
    moved = fine[:, lead] - fine[:, follower]
    bump = (gap[follower] + moved - (arc[lead] - arc[follower]) < 0).any(axis=0)
    hits = [np.stack([follower[bump], lead[bump]], axis=1)]
    if ci.size:
        # Poses of the rows in a pair at every check time; the separating-axis test only where the
        # two circumscribed circles meet.
        rows, inv = np.unique(np.concatenate([ci, cj]), return_inverse=True)
        u = np.minimum(np.maximum(fine[:, rows] / t.ds, 0.0), t.last)
        i0 = np.minimum(u.astype(np.int64), t.last - 1)
        f = u - i0
        r2 = route[rows]
        p0 = t.xy[r2, i0]
        p = p0 + (t.xy[r2, i0 + 1] - p0) * f[..., None]
        m = ci.size
        dd = p[:, inv[m:]] - p[:, inv[:m]]
        radius = 0.5 * np.hypot(length, width)
        near = dd[..., 0] ** 2 + dd[..., 1] ** 2 <= (radius[ci] + radius[cj]) ** 2 + 1e-9
        tk, pk = np.nonzero(near)
        if tk.size:
            h0 = t.heading[r2, i0]
            a = h0 + (t.heading[r2, i0 + 1] - h0) * f
            ai, aj, dd = a[tk, inv[pk]], a[tk, inv[m + pk]], dd[tk, pk]
            c_i, s_i, c_j, s_j = np.cos(ai), np.sin(ai), np.cos(aj), np.sin(aj)
            c, s = np.abs(c_i * c_j + s_i * s_j), np.abs(c_i * s_j - s_i * c_j)
            pi, pj = ci[pk], cj[pk]
            li, wi, lj, wj = 0.5 * length[pi], 0.5 * width[pi], 0.5 * length[pj], 0.5 * width[pj]
            hit = (
                (np.abs(dd[:, 0] * c_i + dd[:, 1] * s_i) < li + lj * c + wj * s)
                & (np.abs(-dd[:, 0] * s_i + dd[:, 1] * c_i) < wi + lj * s + wj * c)
                & (np.abs(dd[:, 0] * c_j + dd[:, 1] * s_j) < lj + li * c + wi * s)
                & (np.abs(-dd[:, 0] * s_j + dd[:, 1] * c_j) < wj + li * s + wi * c)
            )
            pk = np.unique(pk[hit])
            hits.append(np.stack([ci[pk], cj[pk]], axis=1))
    collisions = np.unique(np.sort(np.concatenate(hits), axis=1), axis=0)
    # The new state and its observation.
    arc, speed = x_all[-1], v_all[-1]
    pos, hd, leader, gap = _pose_leaders(t, route, arc, length)
    state[1:] = [arc, speed, length, width, pos, hd, leader, gap]
    entry = t.entry[route]
    inside = -S_REF + (arc - entry) * (S_REF / (exit_ - entry))
    s = np.where(arc < entry, -S_REF + (arc - entry), np.where(arc < exit_, inside, arc - exit_))
    d = pos[None, :, :] - pos[:, None, :]
    c, sn = np.cos(hd)[:, None], np.sin(hd)[:, None]
    lon, lat = d[..., 0] * c + d[..., 1] * sn, d[..., 1] * c - d[..., 0] * sn
    maha = 4.0 * lon**2 / 25.0 + 4.0 * lat**2 / 4.0
    maha[np.arange(n), np.arange(n)] = np.inf
    with np.errstate(divide="ignore"):
        dfeat = np.minimum(1.0 / np.sqrt(maha.min(axis=1)), D_MAX)
    limit = t.limit[route, np.minimum(np.maximum((arc / t.ds).astype(np.int64), 0), t.last)]
    x = np.stack([s * S_SCALE, speed / limit, dfeat], axis=1)
    fol = np.flatnonzero(leader >= 0)
    approaching = exit_ - (arc - length / 2) > 0
    src, dst = np.nonzero(t.conflicts[route[:, None], route[None, :]] & approaching[:, None] & approaching[None, :])
    obs = space._empty()
    e1, e = fol.size, fol.size + src.size
    obs["x"][:n] = x
    obs["node_mask"][:n] = 1
    obs["edge_index"][0, :e1], obs["edge_index"][1, :e1] = leader[fol], fol
    obs["edge_index"][0, e1:e], obs["edge_index"][1, e1:e] = src, dst
    obs["edge_type"][e1:e] = 1
    obs["edge_mask"][:e] = 1
    return obs, collisions


def _fleet(lay: Layout, n: int, rng: np.random.Generator):
    route = rng.integers(0, lay.num_routes, n)
    arc = rng.uniform(3.0, lay.length[route] - 60.0)
    return route, arc, rng.uniform(2.0, 8.0, n)


def _episode_bound(t: Tables, space: GraphSpace, fleet: tuple, acc: np.ndarray) -> float:
    route, arc, speed = fleet
    n = arc.shape[0]
    length, width = np.full(n, 5.0), np.full(n, 2.0)
    start = CLOCK[0]()
    state = [route, arc, speed, length, width, *_pose_leaders(t, route, arc, length)]
    for a in acc:
        bound_step(t, space, state, a)
    return CLOCK[0]() - start


def _episode_ours(
    lay: Layout, space: GraphSpace, fleet: tuple, acc: np.ndarray, simulation: type = Simulation
) -> float:
    route, arc, speed = fleet
    start = CLOCK[0]()
    sim = simulation(lay, HZ_SIM, HZ_POLICY, V_MAX, A_MAX, S_REF, MAX_NODES, B_GOV, RESOLUTION)
    sim.add(route, speed, np.arange(arc.shape[0]), 5.0, 2.0, arc=arc)
    for a in acc:
        sim.step(a)
        scene = sim.scene()
        build_observation(scene, space, S_SCALE, D_MAX, min_mahalanobis(scene))
    return CLOCK[0]() - start


def _make_env():
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    config = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0, "max_vehicles": MAX_NODES,
              "max_edges": MAX_EDGES, "duration": 1e6}  # fmt: skip
    return gym.make("CoopIntersection4Way-v0", config=config)


def _episode_env(env, fleet: tuple, acc: np.ndarray) -> float:
    env.reset(seed=0)
    env.unwrapped.place_vehicles(*fleet)
    action = np.zeros(MAX_NODES, np.float32)
    n = fleet[0].shape[0]
    start = CLOCK[0]()
    for a in acc:
        action[:n] = a / A_MAX
        env.step(action)
    return CLOCK[0]() - start


def time_sides(
    lay: Layout, space: GraphSpace, env, n: int, seconds: float, repeats: int, baseline: tuple | None = None
) -> dict[str, float]:
    """Seconds per policy step of the bound, ours and the whole ``env.step`` on the same fleets.

    Each round draws one fleet and its commands; every side runs that episode ``repeats`` times in
    turn and keeps its fastest run (load bursts on a shared machine hit single runs); the rounds'
    times are summed per side, so all sides are timed on exactly the same work.

    :param seconds: rounds are drawn until this much wall time has passed
    :param baseline: ``(Simulation class, layout)`` of another checkout, timed as side ``"baseline"``
    """
    t, rng = tables(lay), np.random.default_rng(n)
    total = {"bound": 0.0, "ours": 0.0, "env": 0.0}
    if baseline is not None:
        total["baseline"] = 0.0
    steps, begin = 0, time.perf_counter()
    while time.perf_counter() - begin < seconds or steps == 0:
        fleet = _fleet(lay, n, rng)
        acc = rng.uniform(-3.0, 3.0, (EPISODE_STEPS, n))
        total["bound"] += min(_episode_bound(t, space, fleet, acc) for _ in range(repeats))
        total["ours"] += min(_episode_ours(lay, space, fleet, acc) for _ in range(repeats))
        total["env"] += min(_episode_env(env, fleet, acc) for _ in range(repeats))
        if baseline is not None:
            simulation, other = baseline
            total["baseline"] += min(_episode_ours(other, space, fleet, acc, simulation) for _ in range(repeats))
        steps += EPISODE_STEPS
    return {side: value / steps for side, value in total.items()}


def load_baseline(checkout: Path) -> tuple[type, Layout]:
    """The simulation and 4-way layout of another checkout (e.g. ``git worktree add /tmp/old <commit>``),
    imported as separate modules so that both versions run in this process."""
    modules = {}
    for name, grouped in (("layouts", "layouts"), ("simulation", "engine")):
        path = checkout / "envs" / "simulation" / f"{grouped}.py"  # envs/ grouped by question (issue #25)
        if not path.is_file():
            path = checkout / "envs" / f"{name}.py"  # a checkout from before
        spec = importlib.util.spec_from_file_location(f"baseline_{name}", path)
        modules[name] = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = modules[name]  # dataclasses look their module up
        spec.loader.exec_module(modules[name])
    return modules["simulation"].Simulation, modules["layouts"].build_layout("4way")


def _time_stock(n: int, seconds: float, seed: int = 0) -> tuple[float, float]:
    """Stock ``intersection-v0`` (1 Hz policy, 15 Hz simulation), its ego vehicle IDLE, topped up
    to ``n`` vehicles before every step (top-up not timed): vehicles placed at random on the four
    incoming lanes at 2-8 m/s with random destinations and no spacing check, like our fleet (its own
    spawner keeps 15 m between vehicles and saturates near 20).

    :return: wall (or CPU) s per policy step and the mean number of vehicles stepped
    """
    import gymnasium as gym
    import highway_env  # noqa: F401
    from highway_env import utils

    env = gym.make("intersection-v0", config={"spawn_probability": 0.0, "duration": 10_000})
    env.reset(seed=seed)
    base = env.unwrapped
    vehicle_type = utils.class_from_path(base.config["other_vehicles_type"])
    rng = np.random.default_rng(seed)
    steps, counts, wall = 0, [], 0.0
    while wall < seconds:
        while len(base.road.vehicles) < n:
            start_arm, end_arm = rng.choice(4, 2, replace=False)
            lane = (f"o{start_arm}", f"ir{start_arm}", 0)
            vehicle = vehicle_type.make_on_lane(
                base.road, lane, float(rng.uniform(5.0, 85.0)), float(rng.uniform(2, 8))
            )
            vehicle.plan_route_to(f"o{end_arm}")
            vehicle.randomize_behavior()
            base.road.vehicles.append(vehicle)
        counts.append(len(base.road.vehicles))
        start = CLOCK[0]()
        _, _, _, truncated, _ = env.step(1)
        wall += CLOCK[0]() - start
        steps += 1
        if truncated:
            env.reset()
    return wall / steps, float(np.mean(counts))


def _row(label: str, n: str, step_s: float, policy_hz: int, ratio: str) -> str:
    cells = [label, n, f"{1.0 / (step_s * policy_hz):.1f}", f"{1.0 / step_s:.0f}", f"{1e3 * step_s:.3f}", ratio]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0, help="wall time per vehicle count")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each episode (the fastest counts)")
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS), help="vehicle counts")
    parser.add_argument(
        "--clock", choices=("wall", "cpu"), default="wall", help="wall: perf_counter; cpu: process_time"
    )
    parser.add_argument("--no-stock", action="store_true", help="leave out stock intersection-v0")
    parser.add_argument(
        "--baseline", type=Path, help="another checkout whose simulation engine is timed too, interleaved"
    )
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore")
    CLOCK[0] = time.perf_counter if args.clock == "wall" else time.process_time
    per = "wall s" if args.clock == "wall" else "CPU s"
    lay = build_layout("4way")
    space = GraphSpace(MAX_NODES, NODE_FEATURES, MAX_EDGES, NUM_RELATIONS)
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    print(f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, "
          f"Python {platform.python_version()}, NumPy {np.__version__}, load average {load} (start)")  # fmt: skip
    print(f"Command: python {' '.join(sys.argv)}\n")
    print(f"| what | vehicles | simulated s / {per} | policy steps / {per} | ms ({args.clock}) / policy step "
          "| ours / bound |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    env_ = _make_env()
    baseline = load_baseline(args.baseline) if args.baseline else None
    for n in args.counts:
        times = time_sides(lay, space, env_, n, args.seconds, args.repeats, baseline)
        bound, ours, env = times["bound"], times["ours"], times["env"]
        print(_row("NumPy bound (bench_sim_bound.bound_step)", str(n), bound, HZ_POLICY, "1"))
        if baseline is not None:
            label = f"baseline {args.baseline}: Simulation.step + scene + build_observation"
            print(_row(label, str(n), times["baseline"], HZ_POLICY, f"{bound / times['baseline']:.2f}"))
        print(_row("ours: Simulation.step + scene + build_observation", str(n), ours, HZ_POLICY, f"{bound / ours:.2f}"))
        print(_row("ours: whole env.step (+ reward, spawn, info)", str(n), env, HZ_POLICY, f"{bound / env:.2f}"))
        if not args.no_stock:
            stock, mean = _time_stock(n, args.seconds / 6)
            # Like for like in simulated time: our env.step covers 0.2 s, a stock step 1 s.
            faster = (1.0 / (env * HZ_POLICY)) / (1.0 / stock)
            label = f"stock intersection-v0 (1 Hz policy), IDLE: ours (env.step) {faster:.0f}x faster in simulated s"
            print(_row(label, f"{mean:.1f}", stock, 1, "n/a"))
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    print(f"\nLoad average at the end: {load}. ours / bound = bound's ms per step over ours (1: as fast).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
