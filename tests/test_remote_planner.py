"""The remote planner (``http://HOST:PORT``, ``+shield``) survives its server: a restart, an outage, a missed
deadline; each counted, and a miss answered with the vehicle-side fallback.

Servers run in a thread of the test process on a free loopback port (``serve_support.ThreadServer``), and
skip when the ``serve`` extra (FastAPI, uvicorn) is not installed.
"""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
from serve_support import TOKEN, SlowPlanner, ThreadServer, free_port, serve_extra

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner
from envs.planners.shield import Shield
from envs.serve.client import RemotePlanner, RemoteShield
from envs.serve.wire import SceneBuilder

pytestmark = pytest.mark.skipif(not serve_extra(), reason="the 'serve' extra (fastapi, uvicorn) is not installed")
ENV = "CoopIntersection4Way-v0"
SUPPORT = Path(__file__).resolve().parent / "serve_support.py"


@pytest.fixture(scope="module")
def builder():
    env = gym.make(ENV)
    config = dict(env.unwrapped.config)
    env.close()
    return SceneBuilder(config)


def scene(builder, n: int, time_s: float, committed: bool = False):
    """An in-process scene (layout and arcs: what a remote planner sends) of ``n`` vehicles, 10 m apart
    (``committed``: the first one 3 m into the intersection)."""
    lay = builder.layout
    cars = [SimpleNamespace(id=i, route=lay.route_names[i % lay.num_routes], arc=20.0 + 10.0 * i, speed=8.0,
                            length=4.5, width=1.8) for i in range(n)]  # fmt: skip
    if committed:
        cars[0].arc = float(lay.entry_arc[0]) + 3.0
    return builder.scene(lay.name, time_s, cars)


def test_a_server_restart_is_survived(builder, service):
    """The stream is reopened on the restarted server (404 on the old one) and sent this decision's scene;
    while the server is down, decisions miss their deadline, get the fallback and are counted."""
    port = free_port()
    local = make_planner("pr")
    local.reset(0)
    with ThreadServer(service, port=port) as server:
        remote = RemotePlanner(server.url, token=TOKEN, deadline=5.0)
        remote.reset(0)
        for k in range(3):
            s = scene(builder, 3, 0.2 * k)
            np.testing.assert_array_equal(remote.act(s), local.act(s))
        first = remote.stream
    remote.deadline = 0.3
    down = scene(builder, 3, 0.6)
    tic = time.monotonic()
    np.testing.assert_array_equal(remote.act(down), np.full(3, down.a_min))  # everyone brakes
    assert 0.25 < time.monotonic() - tic < 2.0
    assert remote.deadline_misses == 1 and remote.retries >= 2  # backed off and tried again until the deadline
    remote.deadline = 5.0
    with ThreadServer(service, port=port):  # the same address, none of the old streams
        s = scene(builder, 4, 0.8)
        np.testing.assert_array_equal(remote.act(s), local.act(s))
        assert remote.stream != first and remote.reopened == 1
    stats = remote.stats()
    assert stats["remote_deadline_misses"] == 1 and stats["remote_reopened"] == 1 and stats["remote_retries"] >= 2


def test_a_missed_deadline_falls_back_and_the_next_decision_resumes(builder):
    """A server slower than the deadline: the decision brakes (no shield) or takes the shield's fallback
    (``+shield``, the shield's own :meth:`~envs.planners.shield.Shield.check` with every vehicle forced); the
    step the server finished after the miss does not block the next one (its seq is resynchronised)."""
    from envs.serve.app import PlannerService

    service = PlannerService(f"{SUPPORT}:SlowPlanner", ENV)
    slow = scene(builder, SlowPlanner.SLOW_VEHICLES, 0.0, committed=True)
    with ThreadServer(service, workers=1, time_limit=5.0) as server:
        plain = RemotePlanner(server.url, token=TOKEN, deadline=0.25)
        plain.reset(0)
        tic = time.monotonic()
        np.testing.assert_array_equal(plain.act(slow), np.full(slow.num_vehicles, slow.a_min))
        assert time.monotonic() - tic < 0.9 and plain.deadline_misses == 1
        time.sleep(SlowPlanner.SLOW_SECONDS + 0.2)  # the server completes the step it was sent
        quick = scene(builder, 2, 0.2)
        np.testing.assert_array_equal(plain.act(quick), [-1.0, -1.0])  # the server's answer again
        assert plain.deadline_misses == 1 and plain.client.seq[plain.stream] == 2

        shielded = RemoteShield(RemotePlanner(server.url, token=TOKEN, deadline=0.25))
        shielded.reset(0)
        reference = Shield(make_planner("pr"))
        reference.reset(0)
        expected = reference.check(slow, np.zeros(slow.num_vehicles), forced=np.ones(slow.num_vehicles, bool))
        np.testing.assert_array_equal(shielded.act(slow), expected)
        assert not np.allclose(expected, slow.a_min)  # the shield's fallback, not a blanket brake
        stats = shielded.stats()
        assert stats["remote_deadline_misses"] == 1
        assert stats["shield_interventions"] == slow.num_vehicles and stats["planner_errors"] == 0
        time.sleep(SlowPlanner.SLOW_SECONDS + 0.2)


def test_shield_spec_of_a_server_builds_the_remote_shield(service, monkeypatch):
    monkeypatch.delenv("SB3_GRAPH_TOKEN_FILE", raising=False)
    with ThreadServer(service, tokens=()) as server:
        planner = make_planner(server.url + "+shield")
        assert isinstance(planner, RemoteShield) and isinstance(planner, Shield)
        assert planner.planner.raise_on_miss and planner.name.endswith("+shield")


def test_a_restarted_server_process_with_a_fresh_token_is_survived_idle_and_busy(builder, tmp_path, monkeypatch):
    """A real ``sb3-graph serve`` with its default token file, restarted twice on the same port, each time with a
    new token: once while the planner is idle (its kept-alive connection and socket are stale, its token too),
    once while it decides back-to-back (``kill -9``). No decision raises; each gets the server's answer or the
    fallback, and the planner finds the new token and reopens its stream by itself."""
    import signal
    import threading

    from serve_support import serve_process

    from envs.serve.access import default_token_path

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.delenv("SB3_GRAPH_TOKEN_FILE", raising=False)
    port = free_port()
    arguments = ("--planner", "pr", "--port", str(port), "--workers", "0")
    local = make_planner("pr")
    local.reset(0)
    token_file = default_token_path("127.0.0.1", port)
    process, url = serve_process(*arguments, env={"XDG_RUNTIME_DIR": str(tmp_path)})
    try:
        remote = RemotePlanner(url, deadline=10.0)
        remote.reset(0)
        for k in range(3):
            s = scene(builder, 3, 0.2 * k)
            np.testing.assert_array_equal(remote.act(s), local.act(s))
        assert remote.client._sockets or not remote.client.fast  # the fast path, where the server has one
        first_token = token_file.read_text()
        process.terminate()
        process.wait(timeout=30)
        process, _ = serve_process(*arguments, env={"XDG_RUNTIME_DIR": str(tmp_path)})
        assert token_file.read_text() != first_token
        s = scene(builder, 4, 0.8)  # idle restart: the first decision after it
        np.testing.assert_array_equal(remote.act(s), local.act(s))
        assert remote.reopened == 1 and remote.deadline_misses == 0

        remote.deadline = 0.5
        errors, answered = [], []
        stop = threading.Event()

        def decide() -> None:
            k = 0
            while not stop.is_set():
                s = scene(builder, 3, 1.0 + 0.2 * k)
                try:
                    acc = remote.act(s)
                    answered.append((remote.reopened, remote.deadline_misses, np.array_equal(acc, local.act(s))))
                except Exception as error:  # noqa: BLE001 - the point: nothing may raise
                    errors.append(repr(error))
                k += 1
                time.sleep(0.02)

        thread = threading.Thread(target=decide)
        thread.start()
        try:
            time.sleep(0.5)
            process.send_signal(signal.SIGKILL)  # busy restart
            process.wait(timeout=30)
            process, _ = serve_process(*arguments, env={"XDG_RUNTIME_DIR": str(tmp_path)})
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not any(r == 2 and same for r, _, same in answered[-3:]):
                time.sleep(0.1)
        finally:
            stop.set()
            thread.join(timeout=30)
        assert not errors, errors[:3]
        assert remote.reopened == 2 and remote.deadline_misses > 0  # fell back while the server was down
        assert answered[-1][0] == 2 and answered[-1][2]  # then the restarted server's answers again
    finally:
        process.kill()
        process.wait()
