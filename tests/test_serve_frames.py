"""The fast path of the planner server: a stream's steps over one WebSocket as binary frames
(``envs/serve/frames.py``), under the same rules as HTTP (token, ``Host``, ownership, exactly once, the
connection cap, TLS) and answered as in process.

Servers run in a thread of the test process on a free loopback port (``serve_support.ThreadServer``), and skip when
the ``serve`` extra (FastAPI, uvicorn, msgspec, a WebSocket library) is not installed.
"""

from __future__ import annotations

import json
import ssl
from types import SimpleNamespace

import numpy as np
import pytest
from serve_support import OTHER_TOKEN, TOKEN, ThreadServer, serve_extra, wire_scene

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


def test_steps_over_the_socket_are_answered_as_over_http_and_exactly_once(service):
    with ThreadServer(service) as server:
        fast, slow = PlannerClient(server.url, token=TOKEN), PlannerClient(server.url, token=TOKEN, fast=False)
        a, b = fast.open("4way", seed=0), slow.open("4way", seed=0)
        for k in range(4):
            scene = _scene(service, 3 + k, 0.2 * k)
            np.testing.assert_array_equal(fast.step_scene(a, scene), slow.step_scene(b, scene))
        assert list(fast._sockets) == [a] and not slow._sockets
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


def test_bad_frames_name_their_field_and_the_socket_goes_on(service):
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
    with ThreadServer(service) as server:
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


def test_the_upgrade_needs_the_token_the_host_and_the_streams_owner(service):
    with ThreadServer(service, tokens=[TOKEN, OTHER_TOKEN]) as server:
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


def test_the_fast_path_over_tls(tmp_path, service):
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(tmp_path / "cert.pem")
    cert.private_key_pem.write_to_path(tmp_path / "key.pem")
    ca.cert_pem.write_to_path(tmp_path / "ca.pem")
    tls = {"ssl_certfile": str(tmp_path / "cert.pem"), "ssl_keyfile": str(tmp_path / "key.pem")}
    with ThreadServer(service, tls=tls) as server:
        client = PlannerClient(server.url, token=TOKEN, ssl_context=ssl.create_default_context(cafile=str(tmp_path /
                                                                                                          "ca.pem")))
        stream = client.open("4way")
        assert client.step_scene(stream, _scene(service, 3, 0.0)).shape == (3,) and stream in client._sockets


def test_the_compiled_overlap_check_finds_the_numpy_checks_first_pair():
    """``wire._first_overlap`` (compiled) against the (n, n) NumPy forms it replaced, on random crowds: the first
    pair closer than half the narrower width, else the first vehicle overlapping its leader by over half the
    shorter length."""
    from envs.serve.wire import _first_overlap

    rng = np.random.default_rng(3)
    found = deep_found = 0
    for n in (2, 5, 20, 100) * 10:
        x, y, half = rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.uniform(0.4, 2.5, n)
        leader = np.where(rng.random(n) < 0.5, rng.integers(0, n, n), -1)
        gap, length = rng.uniform(-4.0, 10.0, n), rng.uniform(1.5, 12.0, n)
        squared = np.square(x[:, None] - x[None, :]) + np.square(y[:, None] - y[None, :])
        close = squared < np.square(np.minimum(half[:, None], half[None, :]))
        np.fill_diagonal(close, False)
        pairs = np.argwhere(np.triu(close, k=1))
        has = leader >= 0
        deep = np.flatnonzero(has & (gap < -0.5 * np.minimum(length, length[np.where(has, leader, 0)])))
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
