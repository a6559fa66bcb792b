"""Latency and load of the planner server (``sb3-graph serve``) on loopback, bounded in count and time.

Each configuration starts its own server process (``--port 0``, loopback, one event loop, one torch
thread) and drives it with the Python client (:class:`envs.serve.client.PlannerClient`, one kept-alive
connection per stream) from this process:

- **latency**: per decision, the wall time of ``client.step`` (the scene's wire encoding, the HTTP round
  trip, the server's parsing, scene building and planning, the answer's decoding), at 10, 50 and 100
  vehicles, for AIM and the shipped GNN, without and with the server's shield; ``in-proc`` is the same
  planner's ``act`` on the same scenes in this process, ``added`` the difference of the medians. The
  GNN takes at most 64 vehicles (its graphs' ``max_nodes``), so its largest size is 64.
- **throughput**: decisions per second with 1, 8 and 32 streams stepped at once (one thread and one
  connection each), for ``--load-planner`` at ``--load-vehicles``; every refusal or failure is an error.
- **memory**: the server's resident memory (``VmRSS``) before and after ``--churn`` streams opened, stepped
  once and closed (stopped at ``--churn-seconds``; the table says how many ran).
- ``--bad-input``: the malformed-input table, each case's status and the server's one-line answer.

The scenes are synthetic and dense: vehicles queued on every incoming lane, 6.5 m apart from the route
start (6 m where that does not hold them all; a place that would put two vehicles of merging routes in one
spot is left out), nearest the intersection first, at 90 % of their lane limit (planners see the same scene at every
step, the time advancing by one policy period). Times are wall-clock on whatever machine runs this; the
script prints it.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_serve.py                     # everything (about 7 minutes)
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --decisions 100 --churn 2000 --skip-gnn
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --bad-input-only
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --identity --scenarios 3 --duration 60
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --components --sizes 100
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --latency-only --planners aim+shield glide+shield \
        fullthrottle+shield
    PYTHONPATH=$PWD python benchmarks/bench_serve.py --latency-only --scene queue --sizes 10 48  # a full queue
"""

from __future__ import annotations

import argparse
import gc
import http.client
import json
import os
import platform
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "envs" / "pretrained" / "coop_4way_fair" / "best_model.safetensors"
ENV = "CoopIntersection4Way-v0"


# ---------------------------------------------------------------------- malformed input
@dataclass(frozen=True)
class BadCase:
    """One malformed request and what the server must answer.

    :param name: what is wrong
    :param body: the raw body
    :param status: the expected status
    :param field: the field the answer must name
    :param path: the request path (``{stream}`` is the open stream)
    :param token: the token sent (``None``: the right one)
    :param method: HTTP method
    :param content_type: the ``Content-Type`` header
    :param host: the ``Host`` header (``None``: the server's address)
    :param seq: the step's sequence number, relative to the next one (``None``: none sent); put into the
        body's JSON object by :func:`send` when it has one
    """

    name: str
    body: bytes
    status: int
    field: str
    path: str = "/streams/{stream}/step"
    token: str | None = None
    method: str = "POST"
    content_type: str = "application/json"
    host: str | None = None
    seq: int | None = 0


def _vehicle_case(good: dict, i: int, key: str, value: Any) -> bytes:
    vehicles = [dict(v) for v in good["vehicles"]]
    vehicles[i][key] = value
    return json.dumps({**good, "vehicles": vehicles}).encode()


def bad_input_cases(good: dict, max_body: int, max_vehicles: int = 64) -> list[BadCase]:
    """The malformed and hostile cases, built from a valid wire scene of at least 3 vehicles with ``time`` > 0.

    :param good: a valid wire scene (:func:`envs.serve.wire.scene_to_wire`), without ``seq``
    :param max_body: the server's body limit [bytes]
    :param max_vehicles: the server's ``max_vehicles``
    :return: the cases; their time lies far ahead of ``good``'s, so that the stream's valid steps that
        follow each case (at ``good``'s time and after) never make a case's time go back. The stream must
        have answered one step before (the replayed ``seq``).
    """
    good = {**good, "time": good["time"] + 10_000.0}
    v0 = good["vehicles"][0]
    crowd = [{**v0, "id": 10_000 + k} for k in range(max_vehicles + 1)]
    big = [{**v0, "id": 20_000 + k} for k in range(max_body // 60 + 1)]
    pile = [{**v0, "id": 30_000 + k} for k in range(min(8, max_vehicles))]
    dump = lambda scene: json.dumps(scene).encode()  # noqa: E731
    return [
        BadCase("not JSON (cut short)", dump(good)[:-5], 422, "body"),
        BadCase("empty body", b"", 422, "body"),
        BadCase("vehicles missing", dump({k: good[k] for k in ("layout", "time", "captured")}), 422, "vehicles"),
        BadCase("captured missing", dump({k: v for k, v in good.items() if k != "captured"}), 422, "captured"),
        BadCase("captured in the future", dump({**good, "captured": good["captured"] + 3600.0}), 422, "captured"),
        BadCase("vehicles not a list", dump({**good, "vehicles": {"id": 1}}), 422, "vehicles"),
        BadCase("unknown field", _vehicle_case(good, 0, "colour", "red"), 422, "vehicles[0].colour"),
        BadCase("time is a string", dump({**good, "time": "12.0"}), 422, "time"),
        BadCase("speed NaN", _vehicle_case(good, 0, "speed", float("nan")), 422, "vehicles[0].speed"),
        BadCase("arc Infinity", _vehicle_case(good, 1, "arc", float("inf")), 422, "vehicles[1].arc"),
        BadCase("negative speed", _vehicle_case(good, 1, "speed", -1.0), 422, "vehicles[1].speed"),
        BadCase("id not an integer", _vehicle_case(good, 0, "id", 1.5), 422, "vehicles[0].id"),
        BadCase("length zero", _vehicle_case(good, 2, "length", 0.0), 422, "vehicles[2].length"),
        BadCase("length 1e-300", _vehicle_case(good, 2, "length", 1e-300), 422, "vehicles[2].length"),
        BadCase("width 50 m", _vehicle_case(good, 0, "width", 50.0), 422, "vehicles[0].width"),
        BadCase(f"{len(pile)} vehicles on one point", dump({**good, "vehicles": pile}), 422, "vehicles[1].arc"),
        BadCase("unknown route", _vehicle_case(good, 2, "route", "south->moon"), 422, "vehicles[2].route"),
        BadCase("duplicate id", _vehicle_case(good, 1, "id", v0["id"]), 422, "vehicles[1].id"),
        BadCase("arc past the route's end", _vehicle_case(good, 0, "arc", 5000.0), 422, "vehicles[0].arc"),
        BadCase("speed above the cap", _vehicle_case(good, 0, "speed", 99.0), 422, "vehicles[0].speed"),
        BadCase("another layout", dump({**good, "layout": "3way"}), 422, "layout"),
        BadCase("time goes back", dump({**good, "time": 0.0}), 422, "time"),
        BadCase(f"too many vehicles ({max_vehicles + 1})", dump({**good, "vehicles": crowd}), 422, "vehicles"),
        BadCase(f"body over {max_body} bytes", dump({**good, "vehicles": big}), 413, "body"),
        BadCase("seq missing", dump(good), 422, "seq", seq=None),
        BadCase("seq skipped", dump(good), 409, "seq", seq=1),
        BadCase("seq of the last step, another scene", dump(good), 409, "seq", seq=-1),
        BadCase("wrong token", dump(good), 401, "authorization", token="wrong"),
        BadCase("another site's Host (DNS rebinding)", dump(good), 400, "host", host="attacker.example:80"),
        BadCase("text/plain (a cross-site form)", dump(good), 415, "content-type", content_type="text/plain"),
        BadCase("unknown stream", dump(good), 404, "stream", path="/streams/0123456789abcdef/step"),
        BadCase("unknown path", b"", 404, "path", path="/streams/{stream}/jump", method="GET"),
        BadCase("wrong method", b"{}", 405, "method", path="/health", method="PUT"),
        BadCase("reset: seed negative", dump({"seed": -1}), 422, "seed", path="/streams/{stream}/reset", seq=None),
    ]


def send(url: str, case: BadCase, stream: str, token: str | None = None, seq: int | None = None) -> tuple[int, dict]:
    """Send one case on a fresh connection; the status and the JSON answer.

    :param seq: the stream's next sequence number (put into the case's body, shifted by ``case.seq``)
    """
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=30)
    headers = {"Content-Type": case.content_type}
    if case.host is not None:
        headers["Host"] = case.host
    sent = case.token if case.token is not None else token
    if sent:
        headers["Authorization"] = f"Bearer {sent}"
    body = case.body
    if seq is not None and case.seq is not None:
        try:
            scene = json.loads(body)
        except ValueError:
            scene = None
        if isinstance(scene, dict):
            body = json.dumps({**scene, "seq": seq + case.seq}).encode()
    try:
        connection.request(case.method, case.path.format(stream=stream), body=body, headers=headers)
        response = connection.getresponse()
        payload = response.read()
    finally:
        connection.close()
    try:
        reply = json.loads(payload) if payload else {}
    except ValueError:
        reply = {"error": payload[:200].decode(errors="replace")}
    return response.status, reply


# ---------------------------------------------------------------------- scenes and servers
def _scene_builder(env_id: str, n: int):
    """The server's scene builder for ``env_id``, sized for ``n`` vehicles (at least 64)."""
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.serve.wire import SceneBuilder

    env = gym.make(env_id, config={"max_vehicles": max(n, 64)})
    builder = SceneBuilder(dict(env.unwrapped.config))
    env.close()
    return builder


def dense_scene(n: int, time_s: float = 0.0, env: str = ENV, spacing: float = 6.5):
    """A synthetic scene of ``n`` vehicles on the layout of ``env``, ``spacing`` apart (see the module docstring;
    6 m where 6.5 m does not hold ``n``)."""
    from envs.serve.wire import WireError

    builder = _scene_builder(env, n)
    lay = builder.layout
    spawns = sorted(set(lay.route_spawn_lane.tolist()))
    slots = []  # (distance from the entry, spawn lane, k)
    for spawn in spawns:
        routes = np.flatnonzero(lay.route_spawn_lane == spawn)
        top = float(lay.length[routes].min()) - 3.0
        for k, arc in enumerate(np.arange(3.0, top, spacing)):
            slots.append((abs(arc - float(lay.entry_arc[routes[0]]) + 5.0), spawn, k, float(arc)))
    slots.sort()
    cars = []
    for spawn, k, arc in (slot[1:] for slot in slots):
        routes = np.flatnonzero(lay.route_spawn_lane == spawn)
        route = int(routes[k % routes.size])
        limit = float(lay.limit_at(np.array([route]), np.array([arc]))[0])
        cars.append(SimpleCar(len(cars), lay.route_names[route], arc, 0.9 * limit))
    # Slots inside the intersection can put two vehicles of merging routes in one place, which the server
    # refuses: such a slot is left out and the next one taken.
    chosen, rest = cars[:n], cars[n:]
    while True:
        if len(chosen) < n:
            if spacing > 6.0:
                return dense_scene(n, time_s, env, 6.0)
            raise ValueError(f"at most {len(chosen)} vehicles fit the synthetic scene")
        try:
            return builder.scene(lay.name, time_s, chosen), builder
        except WireError as error:
            i = int(error.field.split("[")[1].split("]")[0])
            chosen = chosen[:i] + chosen[i + 1 :] + rest[:1]
            rest = rest[1:]
            for k, car in enumerate(chosen):
                car.id = k


def queue_scene(n: int, time_s: float = 0.0, env: str = ENV, spacing: float = 6.5):
    """``n`` vehicles standing in queues before the stop lines of ``env``'s layout, ``spacing`` apart from 3 m
    before each line back to the route start, the nearest first over the lanes (a jam in which every
    vehicle waits; no vehicle in the intersection).

    :raises ValueError: more vehicles than the queues hold (the 4-way layout: 48)
    """
    builder = _scene_builder(env, n)
    lay = builder.layout
    slots = []  # (distance from the line, spawn lane, k, arc)
    for spawn in sorted(set(lay.route_spawn_lane.tolist())):
        routes = np.flatnonzero(lay.route_spawn_lane == spawn)
        entry = float(lay.entry_arc[routes].min())
        for k, arc in enumerate(np.arange(entry - 3.0, 3.0, -spacing)):
            slots.append((entry - arc, spawn, k, float(arc)))
    if n > len(slots):
        raise ValueError(f"the queues of layout {lay.name!r} hold at most {len(slots)} vehicles")
    cars = []
    for _, spawn, k, arc in sorted(slots)[:n]:
        routes = np.flatnonzero(lay.route_spawn_lane == spawn)
        cars.append(SimpleCar(len(cars), lay.route_names[int(routes[k % routes.size])], arc, 0.0))
    return builder.scene(lay.name, time_s, cars), builder


@dataclass
class SimpleCar:
    id: int
    route: str
    arc: float
    speed: float
    length: float = 4.5
    width: float = 1.8


def start_server(planner: str, *extra: str, wait: float = 300.0) -> tuple[subprocess.Popen, str]:
    """``sb3-graph serve --port 0 ...`` in its own process, once it listens: ``(process, url)``."""
    # a step over --time-limit loses its stream: a stall of a loaded machine must not change a compared run
    command = [sys.executable, "-m", "sb3_graph.cli", "serve", "--planner", planner, "--port", "0",
               "--time-limit", "60", *extra]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        ready, _, _ = select.select([process.stdout], [], [], 1.0)
        if ready:
            line = process.stdout.readline()
            if line.startswith("serving "):
                return process, line.split(" on ")[-1].strip()
            if not line and process.poll() is not None:
                break
    process.kill()
    raise RuntimeError(f"server {planner} did not start: {process.stderr.read()[-2000:]}")


def stop_server(process: subprocess.Popen) -> None:
    process.terminate()
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def rss_mib(pid: int) -> float:
    """Resident memory of a process [MiB] (Linux ``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _ms(values: list[float]) -> tuple[float, float, float]:
    a = np.asarray(values) * 1e3
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max())


# ---------------------------------------------------------------------- measurements
def cpu_s(pid: int) -> float:
    """CPU time (user + system) a process and its living children (the planning processes) have used [s]
    (Linux ``/proc``, 10 ms ticks)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    own = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        children = []
    return own + sum(cpu_s(int(child)) for child in children)


def _remote_step(client, stream: str, scene, transport: str) -> float:
    """Wall time of one remote decision, its encoding included (as in ``RemotePlanner.act``) [s]."""
    from envs.serve.wire import scene_to_wire

    tic = time.perf_counter()
    if transport == "fast":
        client.step_scene(stream, scene)
    else:
        client.step(stream, scene_to_wire(scene))
    return time.perf_counter() - tic


def _local_step(planner, scene) -> tuple[float, float]:
    """Wall and CPU time of one decision in this process [s]."""
    tic, cpu = time.perf_counter(), time.process_time()
    planner.act(scene)
    return time.perf_counter() - tic, time.process_time() - cpu


def latency(
    url: str, pid: int, planner_spec: str, sizes: list[int], decisions: int, seconds: float, scene_kind: str = "dense",
    transport: str = "fast",
) -> list[dict]:
    """Per-decision latency through the server and in process, per scene size, and CPU per decision
    (``scene_kind``: :func:`dense_scene` or :func:`queue_scene`; ``transport``: ``fast``, the client's
    WebSocket with binary frames, or ``http``, JSON over HTTP). The two are timed alternately on the same scene,
    the order swapped every decision, so that both see the same load."""
    from envs.planners import make_planner
    from envs.serve.app import as_served
    from envs.serve.client import PlannerClient
    from envs.serve.wire import scene_to_wire

    rows = []
    client = PlannerClient(url, fast=transport == "fast")
    local = make_planner(planner_spec)
    as_served(local)  # as the server runs it (a lookahead searches beside the steps)
    for n in sizes:
        scene, builder = (queue_scene if scene_kind == "queue" else dense_scene)(n)
        stream = client.open("4way", dt=scene.dt, seed=0)
        local.reset(0)
        remote_t, server_t, local_t = [], [], []
        server_cpu = local_cpu = 0.0
        stop = time.monotonic() + seconds
        warm = 5  # untimed first decisions (the planners' first calls load compiled kernels)
        cars = [SimpleCar(**v) for v in scene_to_wire(scene)["vehicles"]]
        for k in range(-warm, decisions):
            if time.monotonic() > stop:
                break
            if k == 0:
                server_cpu = -cpu_s(pid)
                # this process's long-lived objects (torch, numba, the planner) out of the collector's reach, as
                # the server's are: a full collection walks them for a few hundred ms, in either measurement
                gc.collect()
                gc.freeze()
            at_t = builder.scene("4way", (k + warm) * scene.dt, cars)
            if k % 2:
                (wall, cpu), remote = _local_step(local, at_t), _remote_step(client, stream, at_t, transport)
            else:
                remote, (wall, cpu) = _remote_step(client, stream, at_t, transport), _local_step(local, at_t)
            if k >= 0:
                local_t.append(wall)
                local_cpu += cpu
                remote_t.append(remote)
                server_t.append(client.server_ms / 1e3)
        server_cpu += cpu_s(pid)
        client.close(stream)
        count = len(remote_t)
        p50, p99, worst = _ms(remote_t)
        s50, s99, _ = _ms(server_t)
        l50, l99, _ = _ms(local_t)
        rows.append({"vehicles": n, "decisions": count, "p50": p50, "p99": p99, "max": worst,
                     "in-proc p50": l50, "in-proc p99": l99, "p50 ratio": p50 / l50, "p99 ratio": p99 / l99,
                     "added p50": p50 - l50, "server p50": s50, "server p99": s99,
                     "server CPU": 1e3 * server_cpu / count, "in-proc CPU": 1e3 * local_cpu / count})  # fmt: skip
    client.disconnect()
    return rows


def throughput(url: str, n: int, streams: int, seconds: float, env: str = ENV) -> dict:
    """Decisions per second with ``streams`` streams stepped back-to-back at once (one thread and connection
    each), the latency of their decisions [ms] and the errors by status."""
    from envs.serve.client import PlannerClient, RemotePlannerError
    from envs.serve.wire import scene_to_wire

    scene, _ = dense_scene(n, env=env)
    wire = scene_to_wire(scene)
    times: list[float] = []
    errors: dict[int, int] = {}
    lock = threading.Lock()
    start = threading.Barrier(streams + 1)
    stop_at: list[float] = [0.0]

    def work() -> None:
        client = PlannerClient(url, timeout=30)
        try:
            stream = client.open(wire["layout"], seed=0)
        except RemotePlannerError as error:
            with lock:
                errors[error.status] = errors.get(error.status, 0) + 1
            start.wait()
            return
        start.wait()
        k = 0
        while time.monotonic() < stop_at[0]:
            tic = time.perf_counter()
            try:
                client.step(stream, {**wire, "time": k * scene.dt})
                with lock:
                    times.append(time.perf_counter() - tic)
            except (RemotePlannerError, OSError) as error:
                with lock:
                    status = getattr(error, "status", 0)
                    errors[status] = errors.get(status, 0) + 1
            k += 1
        client.close(stream)
        client.disconnect()

    threads = [threading.Thread(target=work) for _ in range(streams)]
    for thread in threads:
        thread.start()
    stop_at[0] = time.monotonic() + seconds + 0.5  # set before the barrier releases the workers
    start.wait()
    tic = time.monotonic()
    for thread in threads:
        thread.join(timeout=seconds + 60)
    wall = time.monotonic() - tic
    p50, p99, worst = _ms(times) if times else (float("nan"),) * 3
    shown = ", ".join(f"{k}: {v}" for k, v in sorted(errors.items())) or "0"
    return {"streams": streams, "vehicles": n, "decisions": len(times), "decisions/s": len(times) / wall,
            "p50 [ms]": p50, "p99 [ms]": p99, "max [ms]": worst, "errors (status: count)": shown}  # fmt: skip


def concurrency(workers: list[int], small: int, big: int, n_small: int, seconds: float) -> list[dict]:
    """Latency of ``small`` streams of ``n_small`` vehicles, alone and beside one stream of ``big`` vehicles,
    for each number of planning processes (AIM behind the server's shield, every stream back-to-back)."""
    from envs.serve.wire import scene_to_wire

    kwargs = json.dumps({"config": {"max_vehicles": max(big, 64)}})
    small_scene, big_scene = scene_to_wire(dense_scene(n_small)[0]), scene_to_wire(dense_scene(big)[0])
    rows = []
    for count in workers:
        process, url = start_server("aim", "--shield", "--env-kwargs", kwargs, "--workers", str(count),
                                    "--time-limit", "30")  # fmt: skip
        try:
            _streams(url, ["small", "big"], {"small": small_scene, "big": big_scene}, 0.5)  # untimed: compiled kernels
            for with_big in (False, True):
                kinds = (["big"] if with_big else []) + ["small"] * small  # the big stream opens first
                times = _streams(url, kinds, {"small": small_scene, "big": big_scene}, seconds)
                s50, s99, smax = _ms(times["small"])
                b50 = _ms(times["big"])[0] if times["big"] else float("nan")
                rows.append({"workers": count, "load": f"{small} x {n_small} vehicles" + (f" + 1 x {big} vehicles"
                             if with_big else ""), "small decisions": len(times["small"]), "small p50": s50,
                             "small p99": s99, "small max": smax, "big p50": b50,
                             "big decisions": len(times["big"])})  # fmt: skip
        finally:
            stop_server(process)
    return rows


def _streams(url: str, kinds: list[str], scenes: dict[str, dict], seconds: float) -> dict[str, list[float]]:
    """One thread and stream per entry of ``kinds`` (opened one after the other, so that the server spreads
    them over its workers), each stepping ``scenes[kind]`` back-to-back; the latencies [s] per kind."""
    from envs.serve.client import PlannerClient

    times: dict[str, list[float]] = {kind: [] for kind in scenes}
    lock, stop, ready = threading.Lock(), time.monotonic() + seconds + 0.2 * len(kinds), threading.Barrier(len(kinds))

    def work(kind: str) -> None:
        client = PlannerClient(url, timeout=60)
        stream = client.open(scenes[kind]["layout"], seed=0)
        ready.wait()
        k = 0
        while time.monotonic() < stop:
            tic = time.perf_counter()
            client.step(stream, {**scenes[kind], "time": 0.2 * k})
            with lock:
                times[kind].append(time.perf_counter() - tic)
            k += 1
        client.close(stream)

    threads = []
    for kind in kinds:
        threads.append(threading.Thread(target=work, args=(kind,)))
        threads[-1].start()
        time.sleep(0.2)
    for thread in threads:
        thread.join(timeout=seconds + 120)
    return times


# The remote planner's own counters (a run in process has none): left out of the identity's comparison.
REMOTE_COLUMNS = ("remote_deadline_misses", "remote_retries", "remote_reopened")
LOAD_LIMITS = {"clients": 64, "seconds": 120.0, "vehicles": 1024}


def load_test(url: str, clients: int, seconds: float, vehicles: int) -> str:
    """A bounded load test of a running server (one's own): ``clients`` streams stepping back-to-back for
    ``seconds`` seconds on a synthetic scene of ``vehicles`` vehicles of the server's layout."""
    from envs.serve.client import PlannerClient, RemotePlannerError

    for name, value in (("clients", clients), ("seconds", seconds), ("vehicles", vehicles)):
        if not 0 < value <= LOAD_LIMITS[name]:
            raise SystemExit(f"--{name} must be from 1 to {LOAD_LIMITS[name]}, got {value}")
    try:
        info = PlannerClient(url, timeout=10).version()
    except RemotePlannerError as error:
        raise SystemExit(f"--url: {error} (a token: $SB3_GRAPH_TOKEN_FILE)") from None
    n = min(vehicles, int(info["max_vehicles"]))
    row = throughput(url, n, clients, seconds, env=info["env"])
    return (f"server: {info['planner']} (shield: {info['shield']}), {info['env']}, workers {info.get('workers')}\n"
            f"load: {clients} streams x {n} vehicles, back-to-back, {seconds:g} s\n\n" + _table([row], 1))


def churn(url: str, pid: int, count: int, seconds: float) -> dict:
    """Open, step once and close ``count`` streams; the server's memory before and after."""
    from envs.serve.client import PlannerClient
    from envs.serve.wire import scene_to_wire

    scene, _ = dense_scene(10)
    wire = scene_to_wire(scene)
    client = PlannerClient(url)
    for _ in range(50):  # warm the allocator before the first reading
        client.close(stream := client.open("4way"))
    before = rss_mib(pid)
    marks, k, stop = {}, 0, time.monotonic() + seconds
    while k < count and time.monotonic() < stop:
        stream = client.open("4way", seed=0)
        client.step(stream, wire)
        client.close(stream)
        k += 1
        if k in (count // 10, count // 2):
            marks[k] = rss_mib(pid)
    after = rss_mib(pid)
    left = client.health()["streams"]
    client.disconnect()
    return {"streams opened and closed": k, "RSS before [MiB]": before, **{f"RSS after {m} [MiB]": v for m, v in
            marks.items()}, "RSS after [MiB]": after, "streams left open": left}  # fmt: skip


def _table(rows: list[dict], digits: int = 2) -> str:
    if not rows:
        return "(none)"
    keys = list(rows[0])
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for row in rows:
        out.append("| " + " | ".join(f"{row[k]:.{digits}f}" if isinstance(row[k], float) else str(row[k])
                                     for k in keys) + " |")  # fmt: skip
    return "\n".join(out)


def bad_input_table() -> str:
    """Start a server (AIM, a token, a 64 KiB body limit) and send every malformed case."""
    import tempfile

    from envs.serve.client import PlannerClient
    from envs.serve.wire import scene_to_wire

    token = "bench-token-0123456789"
    with tempfile.TemporaryDirectory() as folder:
        token_file = Path(folder) / "token"
        token_file.write_text(token)
        process, url = start_server("aim", "--token-file", str(token_file), "--max-body", "65536")
        try:
            client = PlannerClient(url, token=token)
            scene, _ = dense_scene(10, time_s=10.0)
            good = scene_to_wire(scene)
            stream = client.open("4way", seed=0)
            client.step(stream, good)
            rows = []
            for case in bad_input_cases(good, 65536):
                status, reply = send(url, case, stream, token, seq=client.seq[stream] + 1)
                good = {**good, "time": good["time"] + 0.2}
                client.step(stream, good)  # the stream goes on
                ok = "yes" if (status, reply.get("field")) == (case.status, case.field) else "NO"
                rows.append({"case": case.name, "status": status, "answer": str(reply.get("error", ""))[:90],
                             "as expected": ok, "next valid step": "200"})  # fmt: skip
            client.close(stream)
        finally:
            stop_server(process)
    return _table(rows)


def identity(scenarios: int, duration: float, seed: int, skip_gnn: bool = False) -> str:
    """``sb3-graph evaluate`` with each planner in process and through a server, on the same generated
    scenarios in one run; whether every metrics row and every vehicle row is the same.

    Servers: AIM, the GNN, and the GNN with the server's shield; ``+shield`` after a server's address
    shields it in the client.
    """
    import tempfile

    import pandas as pd

    from envs.serve.client import DEADLINE_VARIABLE
    from sb3_graph.cli import main as cli

    # a real-time deadline on a loaded machine would change runs (each miss is counted): the identity is the point
    os.environ.setdefault(DEADLINE_VARIABLE, "60")
    servers = [("aim", ())] + ([] if skip_gnn else [(str(MODEL), ()), (str(MODEL), ("--shield",))])
    started = [start_server(spec, *extra) for spec, extra in servers]
    try:
        urls = [url for _, url in started]
        pairs = [("aim", urls[0]), ("aim+shield", urls[0] + "+shield")]
        if not skip_gnn:
            pairs += [(str(MODEL), urls[1]), (str(MODEL) + "+shield", urls[1] + "+shield"),
                      (str(MODEL) + "+shield", urls[2])]  # fmt: skip
        words = list(dict.fromkeys(w for pair in pairs for w in pair))
        with tempfile.TemporaryDirectory() as folder:
            out = Path(folder) / "report"
            args = ["evaluate", "--out", str(out), "--scenarios", str(scenarios), "--duration", str(duration),
                    "--seed", str(seed), "--jobs", "1", "--no-progress"] + [a for w in words for a in ("--planner", w)]
            if cli(args) != 0:
                raise RuntimeError("evaluate failed")
            metrics, vehicles = pd.read_csv(out / "metrics.csv"), pd.read_csv(out / "vehicles.csv")
    finally:
        for process, _ in started:
            stop_server(process)
    rows, drop = [], ["planner", "wall_s", "baseline", *REMOTE_COLUMNS]
    names = {w: n for w, n in zip(words, list(dict.fromkeys(metrics["planner"])))}
    for local, remote in pairs:
        a = metrics[metrics.planner == names[local]].drop(columns=drop, errors="ignore").reset_index(drop=True)
        b = metrics[metrics.planner == names[remote]].drop(columns=drop, errors="ignore").reset_index(drop=True)
        va = vehicles[vehicles.planner == names[local]].drop(columns="planner").reset_index(drop=True)
        vb = vehicles[vehicles.planner == names[remote]].drop(columns="planner").reset_index(drop=True)
        rows.append({"in process": names[local], "through the server": names[remote].replace(names[local], "..."),
                     "runs": len(a), "vehicles": int(a["vehicles"].sum()), "metric columns": a.shape[1],
                     "metrics identical": "yes" if a.equals(b) else "NO",
                     "vehicle rows identical": "yes" if va.equals(vb) else "NO"})  # fmt: skip
    return _table(rows)


def components(n: int, repeat: int = 200) -> str:
    """CPU time per call of each piece of one remote decision, in this process (``time.process_time``)."""
    from envs.planners import AIMPlanner, make_planner
    from envs.serve import frames
    from envs.serve.app import PlannerService
    from envs.serve.schema import OpenRequest, SceneIn
    from envs.serve.wire import scene_to_wire

    scene, builder = dense_scene(n)
    wire = {**scene_to_wire(scene), "seq": 1}
    body = json.dumps(wire).encode()
    columns = (scene.layout.name, 0.0, scene.route_names, scene.vehicle_id, scene.route, scene.arc, scene.speed,
               scene.length, scene.width)  # fmt: skip
    frame = frames.encode_step(1, *columns)
    decoded = frames.decode_step(frame)
    table = builder.table_columns(decoded.layout, decoded.routes, decoded.ids, decoded.route, decoded.arc,
                                  decoded.speed, decoded.length, decoded.width)  # fmt: skip
    parsed = SceneIn.model_validate_json(body)
    planner = AIMPlanner()
    planner.reset(0)
    shielded = make_planner("aim+shield")
    shielded.reset(0)
    service = PlannerService("aim", ENV, {"config": {"max_vehicles": max(n, 64)}}, shield=True)
    sid = service.open(OpenRequest(layout=builder.layout.name)).id

    def handle() -> None:  # a new step each call: the stream's last step answered again would not plan
        service.streams[sid].seq, service.streams[sid].answer = 0, None
        service.handle("step", sid, body)

    def handle_frame() -> None:
        service.streams[sid].seq, service.streams[sid].answer = 0, None
        service.handle("frame", sid, frame)

    pieces = {
        "client: scene_to_wire": lambda: scene_to_wire(scene),
        "client: json.dumps of the scene": lambda: json.dumps(wire),
        "server: SceneIn.model_validate_json": lambda: SceneIn.model_validate_json(body),
        "server: json.loads + SceneIn.model_validate": lambda: SceneIn.model_validate(json.loads(body)),
        "server: rebuild the scene (SceneBuilder.scene)": lambda: builder.scene("4way", 0.0, parsed.vehicles),
        "client: encode a step frame (frames.encode_step)": lambda: frames.encode_step(1, *columns),
        "server: decode and check a step frame (frames.decode_step)": lambda: frames.decode_step(frame),
        "server: rebuild the scene from a frame's columns (SceneBuilder.build)": lambda: builder.build(0.0, *table),
        "AIM act (in process)": lambda: planner.act(scene),
        "AIM+shield act (in process)": lambda: shielded.act(scene),
        "server: a whole step of AIM+shield without HTTP (PlannerService.handle)": handle,
        "server: a whole fast-path step of AIM+shield without the socket (PlannerService.handle, frame)": handle_frame,
    }
    rows = []
    for name, call in pieces.items():
        call()
        tic = time.process_time()
        for _ in range(repeat):
            call()
        rows.append({"piece": name, "CPU ms per call": 1e3 * (time.process_time() - tic) / repeat})
    return f"{len(body)} bytes of JSON for {n} vehicles\n\n" + _table(rows, 3)


def _cpu_model() -> str:
    """The processor's name (Linux ``/proc/cpuinfo``; else what ``platform`` says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> int:
    from envs.serve.limits import HTTP_PARSERS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 50, 100])
    parser.add_argument("--decisions", type=int, default=300, help="decisions per size (default: 300)")
    parser.add_argument("--seconds", type=float, default=30.0, help="time cap per size [s] (default: 30)")
    parser.add_argument("--load-planner", default="aim", help="planner of the throughput runs (default: aim)")
    parser.add_argument("--load-vehicles", type=int, default=50, help="vehicles in the throughput scene (default: 50)")
    parser.add_argument("--load-streams", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--load-seconds", type=float, default=5.0, help="duration of each throughput, concurrency "
                        f"and load-test run [s] (default: 5; at most {LOAD_LIMITS['seconds']:g} in --load-test)")
    parser.add_argument("--churn", type=int, default=10_000, help="streams opened and closed (default: 10000)")
    parser.add_argument("--churn-seconds", type=float, default=240.0, help="time cap of the churn [s] (default: 240)")
    parser.add_argument("--skip-gnn", action="store_true", help="AIM only")
    parser.add_argument("--planners", nargs="+", help="only these planners in the latency tables (words of "
                        "`serve --planner`, `+shield` for its `--shield`; e.g. aim+shield glide+shield)")
    parser.add_argument("--scene", choices=["dense", "queue"], default="dense", help="the latency tables' scene: "
                        "'dense' (moving, 6.5 m apart, in the intersection too: the shield finds no safe plan) or "
                        "'queue' (standing before the lines; the 4-way holds 48) (default: dense)")  # fmt: skip
    parser.add_argument("--server-workers", type=int, default=1, help="the server's --workers in the latency "
                        "tables (default: 1; 0 plans on the server's event loop)")
    parser.add_argument("--server-http", default="auto", choices=HTTP_PARSERS, help="the server's "
                        "--http (uvicorn's HTTP parser) in the latency tables (default: auto)")  # fmt: skip
    parser.add_argument("--transport", choices=["fast", "http"], default="fast", help="the client's path in the "
                        "latency tables: 'fast' (a WebSocket per stream, binary frames; the client's default) or "
                        "'http' (JSON over HTTP) (default: fast)")  # fmt: skip
    parser.add_argument("--latency-only", action="store_true", help="only the latency tables")
    parser.add_argument("--bad-input-only", action="store_true", help="only the malformed-input table")
    parser.add_argument("--components", action="store_true", help="only: CPU per piece of a decision, in process")
    parser.add_argument("--identity", action="store_true", help="only: evaluate in process and through servers, "
                        "compared row by row (--scenarios, --duration, --seed)")  # fmt: skip
    parser.add_argument("--scenarios", type=int, default=3, help="scenarios of --identity (default: 3)")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds per run of --identity (default: 60)")
    parser.add_argument("--seed", type=int, default=0, help="seed of --identity's scenarios (default: 0)")
    parser.add_argument("--concurrency", action="store_true", help="only: small streams alone and beside a large "
                        "scene, for each of --workers (AIM+shield)")  # fmt: skip
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="planning processes of --concurrency")
    parser.add_argument("--small-streams", type=int, default=3, help="small streams of --concurrency (default: 3)")
    parser.add_argument("--big-vehicles", type=int, default=100, help="the large scene of --concurrency (default: 100)")
    parser.add_argument("--load-test", action="store_true", help="only: a bounded load test of a running server "
                        "(--url, --clients, --load-seconds, --load-vehicles)")  # fmt: skip
    parser.add_argument("--url", default="http://127.0.0.1:8765", help="server of --load-test (default: "
                        "http://127.0.0.1:8765, loopback)")  # fmt: skip
    parser.add_argument("--clients", type=int, default=4, help=f"streams of --load-test (default: 4, at most "
                        f"{LOAD_LIMITS['clients']})")  # fmt: skip
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    print(f"machine: {platform.node()}, {_cpu_model()}, nproc={os.cpu_count()}, load average {os.getloadavg()[0]:.1f}, "
          f"Python {platform.python_version()}, torch {torch.__version__}")  # fmt: skip
    print(f"command: python benchmarks/bench_serve.py {' '.join(argv if argv is not None else sys.argv[1:])}\n")
    if args.load_test:
        print("## Load test\n")
        print(load_test(args.url, args.clients, args.load_seconds, args.load_vehicles))
        return 0
    if args.concurrency:
        print(f"## Concurrency: {args.small_streams} small streams alone and beside one of {args.big_vehicles} "
              f"vehicles (AIM+shield, back-to-back, {args.load_seconds:g} s per run) [ms]\n")  # fmt: skip
        print(_table(concurrency(args.workers, args.small_streams, args.big_vehicles, 10, args.load_seconds)))
        return 0
    if args.identity:
        print(f"## evaluate in process and through the server ({args.scenarios} scenarios x {args.duration:g} s, "
              f"seed {args.seed})\n")  # fmt: skip
        print(identity(args.scenarios, args.duration, args.seed, args.skip_gnn))
        return 0
    if args.components:
        print(f"## CPU per piece of a decision at {max(args.sizes)} vehicles\n")
        print(components(max(args.sizes)))
        return 0
    if args.bad_input_only:
        print("## Malformed input (each followed by a valid step of the same stream)\n")
        print(bad_input_table())
        return 0
    configs = [("aim", "aim", ()), ("aim", "aim+shield", ("--shield",))]
    if not args.skip_gnn:
        configs += [(str(MODEL), "gnn", ()), (str(MODEL), "gnn+shield", ("--shield",))]
    if args.planners:  # planner words, `+shield` for the server's shield
        configs = [(word.removesuffix("+shield"), word, ("--shield",) if word.endswith("+shield") else ())
                   for word in args.planners]  # fmt: skip
    big = max(max(args.sizes), args.load_vehicles, 64)
    kwargs = json.dumps({"config": {"max_vehicles": big}})
    print("## Latency per decision [ms]\n")
    handed = args.transport == "fast" and args.server_workers > 0 and hasattr(socket, "send_fds")
    print(f"transport: {args.transport}; server: --workers {args.server_workers} --http {args.server_http}"
          f"{' (each WebSocket handed to its planning process)' if handed else ''}\n")  # fmt: skip
    print("p50/p99/max: wall clock of one remote decision (client.step_scene on the fast path, client.step over "
          "HTTP: encode, round trip, decode); in-proc: planner.act in this process on the same scene, timed "
          "alternately with it (the order swapped each decision); ratio: remote / in-proc; added p50: p50 - "
          "in-proc p50; server: the server's own wall time (Server-Timing, HTTP only); server CPU: the server "
          "process's and its workers' CPU time over the decisions / decisions; in-proc CPU: planner.act's CPU "
          "time / decisions\n")  # fmt: skip
    for spec, label, extra in configs:
        gnn = spec == str(MODEL)
        sizes = sorted({min(n, 64) if gnn else n for n in args.sizes})
        env_kwargs = () if gnn else ("--env-kwargs", kwargs)  # the GNN's graphs hold 64 vehicles
        process, url = start_server(spec, *extra, *env_kwargs, "--workers", str(args.server_workers),
                                     "--http", args.server_http)  # fmt: skip
        try:
            local_spec = spec + ("+shield" if extra else "")
            print(f"### {label}\n")
            rows = latency(url, process.pid, local_spec, sizes, args.decisions, args.seconds, args.scene,
                           args.transport)  # fmt: skip
            print(_table(rows) + "\n", flush=True)
        finally:
            stop_server(process)
    if args.latency_only:
        return 0
    print(f"## Throughput, {args.load_planner} at {args.load_vehicles} vehicles, {args.load_seconds:g} s per run\n")
    process, url = start_server(args.load_planner, "--env-kwargs", kwargs, "--max-streams", "64")
    try:
        rows = [throughput(url, args.load_vehicles, k, args.load_seconds) for k in args.load_streams]
        print(_table(rows, 1) + "\n", flush=True)
        print(f"## Memory after streams opened, stepped once (10 vehicles) and closed ({args.load_planner})\n")
        print(_table([churn(url, process.pid, args.churn, args.churn_seconds)], 1) + "\n")
    finally:
        stop_server(process)
    print("## Malformed input (each followed by a valid step of the same stream)\n")
    print(bad_input_table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
