"""The planner server's worker processes: one that dies is replaced (at most a few times a minute per slot),
and a step over ``--time-limit`` has its worker killed and replaced, so that no scene holds a worker.

Servers run in a thread of the test process (``serve_support.ThreadServer``); they skip when the ``serve``
extra (FastAPI, uvicorn) is not installed.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from pathlib import Path

import pytest
from serve_support import TOKEN, SlowPlanner, ThreadServer, serve_extra, wire_scene

from envs.serve.client import PlannerClient, RemotePlannerError

pytestmark = pytest.mark.skipif(not serve_extra(), reason="the 'serve' extra (fastapi, uvicorn) is not installed")
ENV = "CoopIntersection4Way-v0"
SUPPORT = Path(__file__).resolve().parent / "serve_support.py"


def wait_for(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "not within the bound"
        time.sleep(0.02)


def sockets_of(pid: int) -> int:
    """How many sockets the process ``pid`` holds (Linux)."""
    count = 0
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            count += os.readlink(fd).startswith("socket:")
        except OSError:  # closed meanwhile
            continue
    return count


def step_error(client: PlannerClient, sid: str, scene: dict) -> tuple[int, str]:
    with pytest.raises(RemotePlannerError) as caught:
        client.step(sid, scene)
    return caught.value.status, caught.value.field


def test_a_killed_worker_is_replaced_and_its_streams_get_404(service):
    layout = service.builder.layout
    with ThreadServer(service, workers=2) as server:
        client, pool = PlannerClient(server.url, token=TOKEN), server.gateway.pool
        a, b = client.open("4way"), client.open("4way")
        worker = {sid: entry.worker for sid, entry in server.gateway.streams.items()}
        assert sorted(worker.values()) == [0, 1]
        lost, kept = (a, b) if worker[a] == 0 else (b, a)
        old = pool.processes[0].pid
        os.kill(old, signal.SIGKILL)
        wait_for(lambda: pool.restarts == 1 and pool.alive_count() == 2)
        assert pool.processes[0].pid != old
        if os.path.isdir("/proc/self/fd"):  # the new worker holds only its own sockets, no client's connection
            own = 2 if pool.hands else 1  # requests, and the hand-overs of WebSockets
            wait_for(lambda: sockets_of(pool.processes[0].pid) == own, 5.0)  # once it has dropped the server's
        assert step_error(client, lost, wire_scene(2, 0.0, layout)) == (404, "stream")
        assert len(client.step(kept, wire_scene(2, 0.0, layout))) == 2  # the other worker's
        fresh = client.open("4way")
        assert server.gateway.streams[fresh].worker == 0  # the restarted worker has the fewest streams
        assert len(client.step(fresh, wire_scene(3, 0.0, layout))) == 3
        health = client.health()
        assert (health["workers"], health["restarts"], health["lost_streams"], health["streams"]) == (2, 1, 1, 2)


def test_a_step_over_the_time_limit_gets_503_and_its_worker_is_replaced():
    from envs.serve.app import PlannerService

    service = PlannerService(f"{SUPPORT}:SlowPlanner", ENV)
    layout = service.builder.layout
    with ThreadServer(service, workers=1, time_limit=0.3) as server:
        client, pool = PlannerClient(server.url, token=TOKEN), server.gateway.pool
        sid = client.open("4way")
        old = pool.processes[0].pid
        tic = time.monotonic()
        assert step_error(client, sid, wire_scene(SlowPlanner.SLOW_VEHICLES, 0.0, layout)) == (503, "time_limit")
        wait_for(lambda: pool.restarts == 1 and pool.alive_count() == 1)
        assert pool.processes[0].pid != old
        assert step_error(client, sid, wire_scene(2, 0.0, layout)) == (404, "stream")  # lost with its worker
        fresh = client.open("4way")
        assert list(client.step(fresh, wire_scene(2, 0.0, layout))) == [-1.0, -1.0]
        # served well before the slow scene would have let its worker go
        assert time.monotonic() - tic < SlowPlanner.SLOW_SECONDS, time.monotonic() - tic
        assert client.health()["restarts"] == 1


def test_a_step_frame_over_the_time_limit_gets_503_and_its_worker_is_replaced():
    """The fast path is under the same time limit: a step frame that overruns gets a 503 refusal frame and its worker
    is killed and replaced, the stream lost with it."""
    pytest.importorskip("msgspec")
    pytest.importorskip("websockets")
    from types import SimpleNamespace

    from envs.serve.app import PlannerService

    service = PlannerService(f"{SUPPORT}:SlowPlanner", ENV)
    builder = service.builder
    with ThreadServer(service, workers=1, time_limit=0.3) as server:
        client, pool = PlannerClient(server.url, token=TOKEN), server.gateway.pool
        assert client.fast
        sid = client.open("4way")
        old = pool.processes[0].pid
        cars = [SimpleNamespace(**v) for v in wire_scene(SlowPlanner.SLOW_VEHICLES, 0.0, builder.layout)["vehicles"]]
        tic = time.monotonic()
        with pytest.raises(RemotePlannerError) as caught:
            client.step_scene(sid, builder.scene(builder.layout.name, 0.0, cars))
        assert (caught.value.status, caught.value.field) == (503, "time_limit")
        assert time.monotonic() - tic < SlowPlanner.SLOW_SECONDS
        wait_for(lambda: pool.restarts == 1 and pool.alive_count() == 1)
        assert pool.processes[0].pid != old


def test_a_crash_loop_stops_at_the_restart_cap(service, caplog):
    with ThreadServer(service, workers=1, max_restarts=2, restart_window=60.0) as server:
        client, pool = PlannerClient(server.url, token=TOKEN), server.gateway.pool
        with caplog.at_level(logging.WARNING, logger="envs.serve.workers"):
            for k in range(3):
                os.kill(pool.processes[0].pid, signal.SIGKILL)
                if k < 2:
                    wait_for(lambda k=k: pool.restarts == k + 1 and pool.alive_count() == 1)
            wait_for(lambda: pool._down[0])
        assert pool.restarts == 2 and pool.alive_count() == 0
        assert [r.levelname for r in caplog.records if "planning process 0" in r.getMessage()] == [
            "WARNING", "WARNING", "ERROR"]  # fmt: skip
        with pytest.raises(RemotePlannerError) as caught:
            client.open("4way")
        assert (caught.value.status, caught.value.field) == (503, "server")
        assert client.health()["workers"] == 0


def test_a_pool_freezes_what_was_built_before_it():
    """The planners are out of the collector's reach once the pool starts (a full walk of them is a stall)."""
    import gc

    from envs.serve.workers import InlinePool

    gc.unfreeze()
    try:
        built = [[k] for k in range(1000)]  # the planners' objects, made before the pool
        InlinePool(object())
        assert gc.get_freeze_count() >= len(built)
    finally:
        gc.unfreeze()
