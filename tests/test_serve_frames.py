"""The fast path of the planner server: a stream's steps over one WebSocket as binary frames
(``envs/serve/frames.py``), under the same rules as HTTP (token, ``Host``, ownership, exactly once, the
connection cap, TLS) and answered as in process.

Servers run in a thread of the test process on a free loopback port (``serve_support.ThreadServer``), and skip when
the ``serve`` extra (FastAPI, uvicorn, msgspec, a WebSocket library) is not installed.
"""

from __future__ import annotations

import json
import socket
import ssl
import struct
import time
from types import SimpleNamespace

import numpy as np
import pytest
from serve_support import OTHER_TOKEN, TOKEN, ThreadServer, serve_extra, wire_scene

from envs.evaluation.harness import env_config
from envs.serve.client import PlannerClient, RemotePlannerError

pytestmark = pytest.mark.skipif(not serve_extra(), reason="the 'serve' extra (fastapi, uvicorn) is not installed")
pytest.importorskip("websockets")  # the server's WebSocket (uvicorn picks it)
frames = pytest.importorskip("msgspec") and pytest.importorskip("envs.serve.frames")
websocket = pytest.importorskip("envs.serve.websocket")


def _scene(service, n: int, time_s: float):
    """An in-process scene (what RemotePlanner sends) of ``n`` vehicles, as ``wire_scene`` places them."""
    cars = [SimpleNamespace(**v) for v in wire_scene(n, time_s, service.builder.layout)["vehicles"]]
    return service.builder.scene(service.builder.layout.name, time_s, cars)


def _frame(scene, seq: int, **change) -> bytes:
    columns = dict(layout=scene.layout.name, time=scene.time, routes=scene.route_names, ids=scene.vehicle_id,
                   route=scene.route, arc=scene.arc, speed=scene.speed, length=scene.length, width=scene.width)
    columns.update(change)
    return frames.encode_step(seq, **columns)


def _socket(server, stream: str, token: str = TOKEN, host: str | None = None):
    headers = {"Authorization": f"Bearer {token}"}
    if host is not None:
        headers["Host"] = host
    return websocket.WebSocket.connect("127.0.0.1", server.port, f"/streams/{stream}/ws", headers, 10.0)


@pytest.mark.parametrize("workers", [0, 1])
def test_steps_over_the_socket_are_answered_as_over_http_and_exactly_once(service, workers):
    """On the event loop (``workers=0``), and handed to the stream's worker (``envs.serve.handoff``)."""
    with ThreadServer(service, workers=workers) as server:
        fast, slow = PlannerClient(server.url, token=TOKEN), PlannerClient(server.url, token=TOKEN, fast=False)
        a, b = fast.open("4way", seed=0), slow.open("4way", seed=0)
        for k in range(4):
            scene = _scene(service, 3 + k, 0.2 * k)
            np.testing.assert_array_equal(fast.step_scene(a, scene), slow.step_scene(b, scene))
        assert list(fast._sockets) == [a] and not slow._sockets
        assert len(server.gateway.handed) == (1 if workers and server.gateway.pool.hands else 0)
        ws = fast._sockets[a]
        scene = _scene(service, 5, 1.0)
        first = _frame(scene, 5)
        ws.send(first)
        answer = frames.decode_reply(ws.recv(10))
        ws.send(first)  # the answer was lost: the same step again is answered from the cache, not planned
        again = frames.decode_reply(ws.recv(10))
        assert answer["step"] == again["step"] == 5
        np.testing.assert_array_equal(answer["accelerations"], again["accelerations"])
        # the same step over HTTP (a client fallen back) is recognised too: the content decides, not the codec
        body = {**json.loads(json.dumps(_wire(scene))), "seq": 5}
        assert fast.request("POST", f"/streams/{a}/step", body)["step"] == 5
        ws.send(_frame(scene, 5, speed=scene.speed + 0.5))  # another scene under an answered number
        refused = frames.decode_reply(ws.recv(10))
        assert (refused["status"], refused["field"], refused["expected"]) == (409, "seq", 6)
        assert server.gateway.streams[a].client == "token-0"


def _wire(scene) -> dict:
    from envs.serve.wire import scene_to_wire

    return scene_to_wire(scene)


@pytest.mark.parametrize("workers", [0, 1])
def test_bad_frames_name_their_field_and_the_socket_goes_on(service, workers):
    scene = _scene(service, 4, 0.0)
    cases = {
        "body": b"\x93\x01\x02",
        "vehicles[2].speed": _frame(scene, 1, speed=np.array([1.0, 2.0, np.nan, 3.0])),
        "vehicles[1].length": _frame(scene, 1, length=np.array([4.5, 0.0, 4.5, 4.5])),
        "vehicles[0].id": _frame(scene, 1, ids=np.array([-1, 1, 2, 3])),
        "vehicles[3].route": _frame(scene, 1, route=np.array([0, 1, 2, 99])),
        "width": _frame(scene, 1, width=np.array([1.8, 1.8])),
        "layout": _frame(scene, 1, layout="3way"),
        "seq": _frame(scene, 0),
        "time": _frame(scene, 1, time=float("inf")),
        "vehicles[1].arc": _frame(scene, 1, arc=np.array([8.0, 8.0, 28.0, 38.0]),
                                  route=np.zeros(4, np.int64)),  # fmt: skip
    }
    with ThreadServer(service, workers=workers) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        ws = _socket(server, stream)
        for field, frame in cases.items():
            ws.send(frame)
            reply = frames.decode_reply(ws.recv(10))
            assert (reply["status"], reply["field"]) == (422, field), (field, reply)
        ws.send(b"text is not a frame", opcode=0x1)
        assert frames.decode_reply(ws.recv(10))["status"] == 415
        ws.send(_frame(scene, 1))
        assert frames.decode_reply(ws.recv(10))["status"] == 200


@pytest.mark.parametrize("workers", [0, 1])
def test_the_upgrade_needs_the_token_the_host_and_the_streams_owner(service, workers):
    with ThreadServer(service, tokens=[TOKEN, OTHER_TOKEN], workers=workers) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        for token, host in (("wrong-token-0123456789", None), (OTHER_TOKEN, None), (TOKEN, "attacker.example")):
            with pytest.raises(websocket.UpgradeRefused) as caught:
                _socket(server, stream, token, host)
            assert caught.value.status == 403
        with pytest.raises(websocket.UpgradeRefused):
            _socket(server, "0123456789abcdef")  # no such stream
        ws = _socket(server, stream)
        assert any(type(p).__name__.startswith("GuardedWebSocket") for p in server.config.guard.open)
        ws.send(_frame(_scene(service, 2, 0.0), 1))
        assert frames.decode_reply(ws.recv(10))["status"] == 200
        # one socket per stream: a second one replaces the first (a client's sockets are bounded by its streams)
        second = _socket(server, stream)
        with pytest.raises(ConnectionError):
            ws.recv(10)
        second.send(_frame(_scene(service, 2, 0.2), 2))
        assert frames.decode_reply(second.recv(10))["step"] == 2
        # the stream closed over HTTP: the server closes its socket, and a new upgrade for it is refused
        client.request("DELETE", f"/streams/{stream}")
        with pytest.raises(ConnectionError):
            second.recv(10)
        with pytest.raises(websocket.UpgradeRefused):
            _socket(server, stream)


def test_a_refused_upgrade_falls_back_to_http_for_that_step(service):
    """A client whose upgrade is refused (a stale token) steps over HTTP, where the refusal is explained."""
    with ThreadServer(service) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        client.token = "stale-token-0123456789"
        with pytest.raises(RemotePlannerError) as caught:
            client.step_scene(stream, _scene(service, 2, 0.0))
        assert (caught.value.status, caught.value.field) == (401, "authorization") and client.fast
        client.token = TOKEN
        assert client.step_scene(stream, _scene(service, 2, 0.0)).shape == (2,) and stream in client._sockets


@pytest.mark.parametrize("workers", [0, 1])
def test_the_fast_path_over_tls(tmp_path, service, workers):
    """TLS connections stay on the event loop (their keys live there), with workers too."""
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(tmp_path / "cert.pem")
    cert.private_key_pem.write_to_path(tmp_path / "key.pem")
    ca.cert_pem.write_to_path(tmp_path / "ca.pem")
    tls = {"ssl_certfile": str(tmp_path / "cert.pem"), "ssl_keyfile": str(tmp_path / "key.pem")}
    with ThreadServer(service, tls=tls, workers=workers) as server:
        client = PlannerClient(server.url, token=TOKEN, ssl_context=ssl.create_default_context(cafile=str(tmp_path /
                                                                                                          "ca.pem")))
        stream = client.open("4way")
        assert client.step_scene(stream, _scene(service, 3, 0.0)).shape == (3,) and stream in client._sockets
        assert not server.gateway.handed


def test_the_compiled_overlap_check_finds_the_numpy_checks_first_pair():
    """``wire._first_overlap`` (compiled) against the (n, n) NumPy forms it replaced, on random crowds: the first
    pair closer than half the narrower width, else the first vehicle overlapping its leader by over half the
    shorter length with their centres within half the two lengths."""
    from envs.serve.wire import _first_overlap

    rng = np.random.default_rng(3)
    found = deep_found = 0
    for n in (2, 5, 20, 100) * 10:
        x, y, half = rng.uniform(0, 30, n), rng.uniform(0, 30, n), rng.uniform(0.4, 2.5, n)
        leader = np.where(rng.random(n) < 0.5, rng.integers(0, n, n), -1)
        gap, length = rng.uniform(-4.0, 10.0, n), rng.uniform(1.5, 12.0, n)
        squared = np.square(x[:, None] - x[None, :]) + np.square(y[:, None] - y[None, :])
        close = squared < np.square(np.minimum(half[:, None], half[None, :]))
        np.fill_diagonal(close, False)
        pairs = np.argwhere(np.triu(close, k=1))
        has = leader >= 0
        ahead = np.where(has, leader, 0)
        near = squared[np.arange(n), ahead] < np.square(0.5 * (length + length[ahead]))
        deep = np.flatnonzero(has & near & (gap < -0.5 * np.minimum(length, length[ahead])))
        if len(pairs):
            expected = (0, int(pairs[0][0]), int(pairs[0][1]))
        elif deep.size:
            expected = (1, int(leader[deep[0]]), int(deep[0]))
        else:
            expected = (-1, -1, -1)
        assert _first_overlap(np.stack([x, y], axis=1), 2.0 * half, leader, gap, length) == expected
        found += expected[0] == 0
        deep_found += expected[0] == 1
    assert 0 < found < 40 and deep_found > 0


def test_a_follower_past_its_leaders_fork_is_not_two_vehicles_in_one_place():
    """A left-turner stays the leader of the vehicle behind it that goes straight up to its own exit: past the fork
    the follower's arc passes the leader's (a negative gap) while the two are metres apart. The server takes such
    a scene of the simulation (the closed-loop benchmark's 422s); the same arcs on one route it refuses."""
    from envs.serve.wire import SceneBuilder, WireError

    builder = SceneBuilder(env_config("CoopIntersection4Way-v0", None))

    def scene(turner: str):
        cars = [SimpleNamespace(id=0, route="north->south", arc=93.12, speed=10.0, length=5.0, width=2.0),
                SimpleNamespace(id=1, route=turner, arc=95.26, speed=5.86, length=5.0, width=2.0)]  # fmt: skip
        return builder.scene("4way", 0.0, cars)

    forked = scene("north->west")
    assert forked.leader[0] == 1 and forked.gap[0] < -2.5  # the simulation's own relation
    with pytest.raises(WireError, match="overlaps vehicle 1"):
        scene("north->south")


def _handed_server(service, **gateway):
    server = ThreadServer(service, workers=1, **gateway)
    if not server.gateway.pool.hands:
        pytest.skip("descriptors cannot be passed between processes here")
    return server


def _raw(ws, n: int) -> bytes:
    """``n`` bytes straight off the socket (what the server sent, frame headers and all)."""
    data = bytes(ws._buffer)
    ws.sock.settimeout(10)
    while len(data) < n:
        chunk = ws.sock.recv(n - len(data))
        if not chunk:
            break
        data += chunk
    return data


def test_a_handed_socket_speaks_the_protocol(service):
    """The worker's end (``envs.serve.handoff``): pings answered, fragments joined, the close echoed; an unmasked
    frame (1002) and a message over the body limit (1009) close the connection."""
    scene = _scene(service, 3, 0.0)
    with _handed_server(service, max_body=4096) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        ws = _socket(server, stream)
        ws.send(b"are you there", opcode=0x9)
        assert _raw(ws, 15) == b"\x8a\x0dare you there"
        frame = _frame(scene, 1)
        ws.sock.sendall(_masked_frame(frame[:10], opcode=0x2, fin=False) + _masked_frame(frame[10:], opcode=0x0))
        assert frames.decode_reply(ws.recv(10))["step"] == 1
        assert len(server.gateway.handed) == 1
        ws.send(struct.pack("!H", 1000), opcode=0x8)
        assert _raw(ws, 4) == b"\x88\x02\x03\xe8"
        wait_for(lambda: not server.gateway.handed and not server.gateway.sockets)
        for bad, code in ((b"\x82\x01x", 1002), (_masked_frame(b"x" * 5000, opcode=0x2), 1009)):
            ws = _socket(server, stream)
            ws.sock.sendall(bad)
            assert _raw(ws, 4) == b"\x88\x02" + struct.pack("!H", code)
        ws = _socket(server, stream)  # the stream goes on
        ws.send(_frame(scene, 2))
        assert frames.decode_reply(ws.recv(10))["step"] == 2


def test_a_client_that_does_not_read_holds_only_its_own_answers(service):
    """A client that sends steps and reads none of the answers does not stall the worker: another stream on the
    same worker is answered, and the idle one's answers wait for it."""
    scene = _scene(service, 12, 0.0)
    with _handed_server(service) as server:
        client = PlannerClient(server.url, token=TOKEN)
        greedy, other = client.open("4way"), client.open("4way")
        ws = _socket(server, greedy)
        ws.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        replay = _frame(scene, 1)
        ws.send(replay)
        sent = 1
        ws.sock.settimeout(0.5)
        try:
            for _ in range(20_000):  # the same step again and again: answered from the cache, never read
                ws.send(replay, timeout=0.5)
                sent += 1
        except (TimeoutError, OSError):
            pass
        tic = time.monotonic()
        assert client.step_scene(other, scene).shape == (12,)
        assert time.monotonic() - tic < 5.0
        assert sent > 100  # the worker read on until its answers filled the socket


def test_handed_streams_expire_only_when_idle(service):
    """Steps on a handed connection are seen by its worker only; the idle expiry asks it before closing."""
    with _handed_server(service, stream_timeout=1.0) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        ws = _socket(server, stream)
        for k in range(8):  # 2.4 s of steps, over twice the timeout
            ws.send(_frame(_scene(service, 2, 0.2 * k), k + 1))
            assert frames.decode_reply(ws.recv(10))["status"] == 200
            time.sleep(0.3)
        assert stream in server.gateway.streams
        wait_for(lambda: stream not in server.gateway.streams, 5.0)
        with pytest.raises(ConnectionError):
            ws.recv(10)
        wait_for(lambda: not server.gateway.handed)


def test_a_lost_worker_closes_its_handed_sockets(service):
    import os
    import signal

    with _handed_server(service) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        assert client.step_scene(stream, _scene(service, 2, 0.0)).shape == (2,)
        ws = client._sockets[stream]
        os.kill(server.gateway.pool.processes[0].pid, signal.SIGKILL)
        with pytest.raises(ConnectionError):
            ws.recv(10)
        wait_for(lambda: server.gateway.pool.alive_count() == 1 and not server.gateway.handed)
        fresh = client.open("4way")
        assert client.step_scene(fresh, _scene(service, 2, 0.0)).shape == (2,)


def test_a_stopped_worker_holding_a_socket_is_replaced(service):
    """A worker that holds a handed connection and stops between steps (``SIGSTOP``) is caught by its heartbeat:
    killed and replaced within the time limit, as one stuck in a step would be."""
    import os
    import signal

    with _handed_server(service, time_limit=0.3) as server:
        client, pool = PlannerClient(server.url, token=TOKEN), server.gateway.pool
        stream = client.open("4way")
        assert client.step_scene(stream, _scene(service, 2, 0.0)).shape == (2,)
        old = pool.processes[0].pid
        os.kill(old, signal.SIGSTOP)
        wait_for(lambda: pool.restarts == 1 and pool.alive_count() == 1, 5.0)
        assert pool.processes[0].pid != old and not server.gateway.handed
        fresh = client.open("4way")
        assert client.step_scene(fresh, _scene(service, 2, 0.0)).shape == (2,)


def _masked_frame(payload: bytes, opcode: int, fin: bool = True) -> bytes:
    n = len(payload)
    head = bytes([(0x80 if fin else 0) | opcode])
    head += bytes([0x80 | n]) if n < 126 else (bytes([0x80 | 126]) + struct.pack("!H", n) if n < 1 << 16 else
                                               bytes([0x80 | 127]) + struct.pack("!Q", n))  # fmt: skip
    return head + b"\0\0\0\0" + payload  # a zero mask: the payload as it is


def wait_for(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "not within the bound"
        time.sleep(0.02)


def test_a_server_of_a_sumo_networks_junction_answers_both_paths_as_in_process(tmp_path):
    """A server whose environment runs on ``net:FILE`` (here the 4-way with 200 m approaches, written as a SUMO
    network: it holds 100 vehicles in closed loop) takes that layout's long name over HTTP and over the socket, and
    answers as its planner does in process; a name longer than the wire allows is refused, naming the field."""
    pytest.importorskip("sumolib")
    from envs.planners import make_planner
    from envs.serve.app import PlannerService
    from envs.serve.wire import MAX_LAYOUT_NAME
    from envs.simulation.layouts import build_layout
    from envs.simulation.sumo_network import write_network

    long = build_layout("4way", access_length=200.0)
    assert np.allclose(long.entry_arc - build_layout("4way").entry_arc, 120.0)
    name = "net:" + str(write_network(long, tmp_path / "net").net_file)
    service = PlannerService("glide", "CoopIntersection4Way-v0", {"config": {"layout": name}})
    assert service.builder.layout.name == name and len(name) > 32
    planner = make_planner("glide")
    planner.reset(0)
    with ThreadServer(service, workers=0) as server:
        fast, slow = PlannerClient(server.url, token=TOKEN), PlannerClient(server.url, token=TOKEN, fast=False)
        a, b = fast.open(name, seed=0), slow.open(name, seed=0)
        for k in range(3):
            scene = _scene(service, 4 + k, 0.2 * k)
            expected = planner.act(scene.copy())
            np.testing.assert_array_equal(fast.step_scene(a, scene), expected)
            np.testing.assert_array_equal(slow.step_scene(b, scene), expected)
        with pytest.raises(RemotePlannerError, match="layout"):
            slow.open("net:" + "x" * MAX_LAYOUT_NAME)
