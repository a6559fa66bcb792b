"""The planner server against the attacks of its threat model (docs/serve.md): each one refused, bounded, or
survived while a good client is still served.

Servers run in a thread of the test process on a free loopback port (``serve_support.ThreadServer``, the
command's uvicorn settings), and skip when the ``serve`` extra (FastAPI, uvicorn) is not installed.
"""

from __future__ import annotations

import http.client
import json
import logging
import os
import resource
import socket
import ssl
import stat
import subprocess
import sys
import threading
import time
from argparse import Namespace
from pathlib import Path

import pytest
from serve_support import OTHER_TOKEN, TOKEN, SlowPlanner, ThreadServer, serve_extra, wire_scene

from envs.serve.client import PlannerClient, RemotePlannerError

pytestmark = pytest.mark.skipif(not serve_extra(), reason="the 'serve' extra (fastapi, uvicorn) is not installed")
ENV = "CoopIntersection4Way-v0"
SUPPORT = Path(__file__).resolve().parent / "serve_support.py"


def raw(url: str, method: str, path: str, body: bytes = b"", headers: dict | None = None) -> tuple[int, dict]:
    """One request on a fresh connection, headers exactly as given (plus Host unless given)."""
    host, port = url.split("//")[1].split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=10)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        payload = response.read()
    finally:
        connection.close()
    return response.status, (json.loads(payload) if payload else {})


def test_default_token_file_is_private_and_found_by_the_client(tmp_path, monkeypatch, service):
    from envs.commands.serve import _access

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.delenv("SB3_GRAPH_TOKEN_FILE", raising=False)
    args = Namespace(allowed_host=[], no_token=False)
    port = 40000 + os.getpid() % 20000
    access = _access(args, None, "127.0.0.1", port)
    path = tmp_path / "sb3-graph" / f"serve-127.0.0.1-{port}.token"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    token = path.read_text().strip()
    assert len(token) >= 32 and access.tokens == [token.encode()]
    assert PlannerClient(f"http://127.0.0.1:{port}").token == token  # the same user's client finds it
    assert _access(args, None, "127.0.0.1", port).tokens != access.tokens  # a new token at every start


def test_no_token_wrong_host_and_text_plain_are_refused_before_parsing(service):
    scene = json.dumps(wire_scene(2, 0.0, service.builder.layout)).encode()
    with ThreadServer(service, tokens=[TOKEN, OTHER_TOKEN], hosts=["planner.local"]) as server:
        bearer = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        assert raw(server.url, "POST", "/streams", b'{"layout": "4way"}', {"Content-Type": "application/json"}) == (
            401, {"error": "authorization: missing or wrong token (send 'Authorization: Bearer <token>')",
                  "field": "authorization"})  # fmt: skip
        # DNS rebinding: a page of attacker.example that resolves to 127.0.0.1 sends its own Host
        status, reply = raw(server.url, "GET", "/version", headers={**bearer, "Host": "attacker.example"})
        assert (status, reply["field"]) == (400, "host")
        assert raw(server.url, "GET", "/version", headers={**bearer, "Host": "planner.local:8765"})[0] == 200
        # a cross-site form posts text/plain without a preflight: refused before its body is read
        for kind in ("text/plain", "application/x-www-form-urlencoded", ""):
            status, reply = raw(server.url, "POST", "/streams", b"not even json", {**bearer, "Content-Type": kind})
            assert (status, reply["field"]) == (415, "content-type"), kind
        # every token of the file is a client; each is served
        for token in (TOKEN, OTHER_TOKEN):
            client = PlannerClient(server.url, token=token)
            stream = client.open("4way")
            assert client.step(stream, json.loads(scene)).shape == (2,)
            client.close(stream)


def test_a_thousand_streams_from_one_client_leave_room_for_another(service):
    with ThreadServer(service, tokens=[TOKEN, OTHER_TOKEN], max_streams=1000, max_streams_per_client=16) as server:
        greedy = PlannerClient(server.url, token=TOKEN)
        opened, refused = 0, []
        for _ in range(1000):
            try:
                greedy.open("4way")
                opened += 1
            except RemotePlannerError as error:
                refused.append((error.status, error.field))
        assert opened == 16 and refused == [(429, "streams")] * 984
        other = PlannerClient(server.url, token=OTHER_TOKEN)
        stream = other.open("4way")
        assert other.step(stream, wire_scene(3, 0.0, service.builder.layout)).shape == (3,)
        # a client cannot see, step or close another's stream
        with pytest.raises(RemotePlannerError) as caught:
            greedy.close(stream)
        assert (caught.value.status, caught.value.field) == (404, "stream")


def test_idle_streams_expire_on_a_timer(service):
    with ThreadServer(service, stream_timeout=0.3) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way")
        assert client.health()["streams"] == 1
        time.sleep(1.0)  # nobody opens a stream meanwhile: the timer alone expires it
        assert client.health()["streams"] == 0 and server.gateway.expired == 1
        with pytest.raises(RemotePlannerError) as caught:
            client.step(stream, wire_scene(1, 0.0, service.builder.layout))
        assert (caught.value.status, caught.value.field) == (404, "stream")


def test_a_replayed_sequence_number_is_answered_from_the_cache(service):
    layout = service.builder.layout
    with ThreadServer(service) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way", seed=0)
        first = json.dumps({**wire_scene(3, 0.0, layout), "seq": 1}).encode()
        headers = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        status, answer = raw(server.url, "POST", f"/streams/{stream}/step", first, headers)
        assert status == 200 and answer["step"] == 1
        # the client lost the answer and sends the step again: the same answer, not planned again
        assert raw(server.url, "POST", f"/streams/{stream}/step", first, headers) == (200, answer)
        second = {**wire_scene(3, 0.2, layout), "seq": 1}  # another scene under an answered number
        status, reply = raw(server.url, "POST", f"/streams/{stream}/step", json.dumps(second).encode(), headers)
        assert (status, reply["field"], reply["expected"]) == (409, "seq", 2)
        status, reply = raw(server.url, "POST", f"/streams/{stream}/step",
                            json.dumps({**second, "seq": 7}).encode(), headers)  # fmt: skip
        assert (status, reply["field"], reply["expected"]) == (409, "seq", 2)
        status, reply = raw(server.url, "POST", f"/streams/{stream}/step",
                            json.dumps({**second, "seq": 2}).encode(), headers)  # fmt: skip
        assert status == 200 and reply["step"] == 2


def _fd_attack(url: str, count: int, seconds: float, threads: int = 8) -> subprocess.Popen:
    """A process that opens ``count`` connections, sends half a request on each and holds them, from ``threads``
    threads (a connect that the full backlog holds back waits for the SYN's retry, a second or more: one thread
    would wait out each of them in turn)."""
    host, port = url.split("//")[1].split(":")
    code = f"""
import socket, threading, time, resource
resource.setrlimit(resource.RLIMIT_NOFILE, resource.getrlimit(resource.RLIMIT_NOFILE)[1:] * 2)
end = time.monotonic() + {seconds}

def attack(count):
    held = []
    while time.monotonic() < end:
        while len(held) < count:
            s = socket.create_connection(({host!r}, {port}))
            s.sendall(b"POST /streams HTTP/1.1\\r\\nHost: 127.0.0.1\\r\\nContent-Le")
            held.append(s)
        time.sleep(0.05)
        held = [s for s in held if s.fileno() >= 0]
        alive = []
        for s in held:  # a connection the server closed reads as EOF: open another
            s.setblocking(False)
            try:
                gone = s.recv(1) == b""
            except BlockingIOError:
                gone = False
            (s.close() if gone else alive.append(s))
        held = alive

shares = [{count} // {threads} + (k < {count} % {threads}) for k in range({threads})]
for t in [threading.Thread(target=attack, args=(n,), daemon=True) for n in shares]:
    t.start()
time.sleep(max(0.0, end - time.monotonic()))
"""
    return subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE)


def test_half_open_connections_leave_a_good_client_served(service):
    """About 3x the connections the file-descriptor limit allows, each half-sent and held, while a good client
    steps a stream: the cap (under the lowered limit) closes the oldest half-open one for each newcomer."""
    from envs.commands.serve import connection_cap

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    used = len(os.listdir("/proc/self/fd"))
    if used > 120:
        pytest.skip(f"this process already holds {used} descriptors")
    resource.setrlimit(resource.RLIMIT_NOFILE, (used + 130, hard))  # a small limit for this test's server
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    for name in ("asyncio", "uvicorn.error"):
        logging.getLogger(name).addHandler(handler)
    attack = None
    try:
        cap = connection_cap(None, 0)
        assert cap < used + 130 - 32
        with ThreadServer(service, max_connections=cap, header_timeout=2.0) as server:
            guard = server.config.guard
            attack = _fd_attack(server.url, 3 * cap, seconds=90.0)
            client = PlannerClient(server.url, token=TOKEN, timeout=5)
            stream = client.open("4way")
            # The short backlog makes the kernel, not the server, hold the flood; on a busy machine the
            # attacker takes a while to open them all (34 of 66 in 20 s once, beside other jobs).
            deadline = time.monotonic() + 45
            while len(guard.open) < cap and time.monotonic() < deadline:
                time.sleep(0.1)
            assert len(guard.open) == cap  # the attack fills the cap
            peak, tic = 0, time.monotonic()
            for k in range(20):
                client.disconnect()  # a new connection each time: the hard case
                assert client.step(stream, wire_scene(2, 0.2 * k, service.builder.layout)).shape == (2,)
                peak = max(peak, len(guard.open))
                time.sleep(0.1)
            took = time.monotonic() - tic
            assert guard.evicted > 0 and peak <= cap
            assert took < 15, took
    finally:
        if attack is not None:
            attack.kill()
            attack.wait()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        for name in ("asyncio", "uvicorn.error"):
            logging.getLogger(name).removeHandler(handler)
    assert not [r for r in records if "accept" in r.getMessage()]  # never out of descriptors
    assert len(records) <= 25  # rate-limited


@pytest.mark.parametrize("http", ["h11", "httptools"])
def test_a_half_sent_request_is_closed_after_the_header_timeout(service, http):
    """With either HTTP implementation (the serve extra installs httptools, which uvicorn then prefers)."""
    if http == "httptools":
        pytest.importorskip("httptools")
    with ThreadServer(service, header_timeout=0.5, http=http) as server:
        expected = {"h11": "GuardedH11Protocol", "httptools": "GuardedHttpToolsProtocol"}[http]
        assert server.config.http.__name__ == expected
        client = PlannerClient(server.url, token=TOKEN, timeout=5)
        assert client.step(client.open("4way"), wire_scene(2, 0.0, service.builder.layout)).shape == (2,)
        with socket.create_connection(("127.0.0.1", server.port)) as lazy, socket.create_connection(
            ("127.0.0.1", server.port)
        ) as silent:
            lazy.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            lazy.settimeout(5)
            silent.settimeout(5)
            tic = time.monotonic()
            assert lazy.recv(100) == b"" and silent.recv(100) == b""  # closed by the server
            assert 0.4 < time.monotonic() - tic < 3


def test_log_is_rate_limited():
    from envs.serve.limits import RateLimitFilter

    limiter = RateLimitFilter(burst=5, rate=0.0)
    logger = logging.getLogger("test_serve_limits.flood")
    logger.addFilter(limiter)
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    logger.addHandler(handler)
    try:
        for k in range(10_000):
            logger.warning("socket.accept() out of system resource %d", k)
    finally:
        logger.removeHandler(handler)
    assert len(records) == 5 and limiter.dropped == 9_995


def test_workers_plan_streams_in_parallel_under_a_time_limit():
    """A slow scene on one worker holds neither the streams of the other worker nor its client past the
    time limit; its worker is killed and replaced, so that its retry finds the stream lost (404)."""
    from envs.serve.app import PlannerService

    service = PlannerService(f"{SUPPORT}:SlowPlanner", ENV)
    layout = service.builder.layout
    with ThreadServer(service, workers=2, time_limit=0.4) as server:
        slow, fast = PlannerClient(server.url, token=TOKEN), PlannerClient(server.url, token=TOKEN)
        a, b = slow.open("4way"), fast.open("4way")
        assert {entry.worker for entry in server.gateway.streams.values()} == {0, 1}
        big = wire_scene(SlowPlanner.SLOW_VEHICLES, 0.0, layout)
        outcome = {}

        def step_slow() -> None:
            try:
                slow.step(a, big)
            except RemotePlannerError as error:
                outcome["error"] = (error.status, error.field)

        thread = threading.Thread(target=step_slow)
        tic = time.monotonic()
        thread.start()
        times = []
        for k in range(5):
            t0 = time.monotonic()
            fast.step(b, wire_scene(2, 0.2 * k, layout))
            times.append(time.monotonic() - t0)
        thread.join()
        assert outcome["error"] == (503, "time_limit") and time.monotonic() - tic < SlowPlanner.SLOW_SECONDS + 0.5
        assert max(times) < 0.35, times  # not held by the slow scene of the other worker
        body = json.dumps({**big, "seq": 1}).encode()
        headers = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        status, reply = raw(server.url, "POST", f"/streams/{a}/step", body, headers)
        assert (status, reply["field"]) == (404, "stream")
        deadline = time.monotonic() + 10
        while server.gateway.pool.alive_count() < 2:  # the killed worker's replacement
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert server.gateway.pool.restarts == 1 and len(fast.step(b, wire_scene(2, 1.0, layout))) == 2


def _certificates(tmp_path: Path):
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    server_cert = ca.issue_cert("127.0.0.1", "localhost")
    client_cert = ca.issue_cert("client@example")
    paths = {name: tmp_path / f"{name}.pem" for name in ("ca", "cert", "key", "client")}
    ca.cert_pem.write_to_path(paths["ca"])
    server_cert.cert_chain_pems[0].write_to_path(paths["cert"])
    server_cert.private_key_pem.write_to_path(paths["key"])
    client_cert.private_key_and_cert_chain_pem.write_to_path(paths["client"])
    return paths


def test_tls_and_mutual_tls(tmp_path, service):
    paths = _certificates(tmp_path)
    trusted = ssl.create_default_context(cafile=str(paths["ca"]))
    tls = {"ssl_certfile": str(paths["cert"]), "ssl_keyfile": str(paths["key"])}
    with ThreadServer(service, tls=tls) as server:
        assert server.url.startswith("https://")
        client = PlannerClient(server.url, token=TOKEN, ssl_context=trusted)
        assert client.version()["planner"] == "PR"
        with pytest.raises(RemotePlannerError):  # the system's CAs do not know the test CA
            PlannerClient(server.url, token=TOKEN, ssl_context=ssl.create_default_context()).version()
    mutual = {**tls, "ssl_ca_certs": str(paths["ca"]), "ssl_cert_reqs": ssl.CERT_REQUIRED}
    with ThreadServer(service, tls=mutual) as server:
        with pytest.raises(RemotePlannerError) as caught:  # no client certificate
            PlannerClient(server.url, token=TOKEN, ssl_context=trusted).version()
        assert caught.value.status == 0
        signed = ssl.create_default_context(cafile=str(paths["ca"]))
        signed.load_cert_chain(str(paths["client"]))
        assert PlannerClient(server.url, token=TOKEN, ssl_context=signed).version()["planner"] == "PR"


def test_openapi_states_the_token_enums_and_limits(service):
    with ThreadServer(service) as server:
        schema = PlannerClient(server.url, token="").request("GET", "/openapi.json")
    assert schema["components"]["securitySchemes"]["bearer"] == {"type": "http", "scheme": "bearer",
                                                                 "description": "a token of the server's token file"}
    assert schema["security"] == [{"bearer": []}] and schema["paths"]["/health"]["get"]["security"] == []
    parts = schema["components"]["schemas"]
    assert parts["SceneIn"]["properties"]["vehicles"]["maxItems"] == service.builder.limits.max_vehicles == 64
    assert parts["SceneIn"]["properties"]["layout"]["enum"] == ["4way"]
    assert parts["Vehicle"]["properties"]["route"]["enum"] == list(service.builder.layout.route_names)
    assert parts["SceneIn"]["properties"]["seq"]["minimum"] == 1
    assert parts["Vehicle"]["properties"]["length"]["minimum"] >= 1.0
    assert schema["paths"]["/streams"]["post"]["requestBody"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/OpenRequest"
    }


def test_an_unknown_http_implementation_is_refused_naming_the_choices():
    from envs.serve.limits import uvicorn_protocol

    with pytest.raises(ValueError, match="http must be one of 'auto', 'httptools', 'h11', got 'h2'"):
        uvicorn_protocol("h2")


def _flood(url: str, count: int, seconds: float, kind: str) -> subprocess.Popen:
    """A process that holds ``count`` connections for ``seconds``: ``handshake``, each open and silent (a TLS
    handshake never begun); ``headers``, each streaming header bytes without end (1 KiB per 10 ms). A connection
    the server closes is opened again."""
    host, port = url.split("//")[1].split(":")
    code = f"""
import socket, time
held, end = [], time.monotonic() + {seconds}
while time.monotonic() < end:
    while len(held) < {count}:
        s = socket.create_connection(({host!r}, {port}))
        s.setblocking(False)
        if {kind!r} == "headers":
            s.sendall(b"GET /health HTTP/1.1\\r\\nHost: 127.0.0.1\\r\\nX-Stream: ")
        held.append(s)
    time.sleep(0.01)
    alive = []
    for s in held:
        try:
            if {kind!r} == "headers":
                s.send(b"a" * 1024)
            gone = s.recv(4096) == b""
        except BlockingIOError:
            gone = False
        except OSError:
            gone = True
        (s.close() if gone else alive.append(s))
    held = alive
"""
    return subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE)


def _good_requests(client: PlannerClient, count: int) -> list[float]:
    """Wall time of ``count`` requests of a good client, each on a new connection (the hard case) [s]."""
    times = []
    for _ in range(count):
        client.disconnect()
        tic = time.monotonic()
        assert client.version()["planner"] == "PR"
        times.append(time.monotonic() - tic)
        time.sleep(0.05)
    return times


def test_idle_tls_handshakes_leave_a_good_client_answered(tmp_path, service):
    """Three times the connection cap in connections that never begin their TLS handshake: each counts from its
    accept, the oldest is closed for a newcomer, and none outlives the header timeout; a good client (mutual TLS)
    is answered at once on new connections throughout."""
    paths = _certificates(tmp_path)
    mutual = {"ssl_certfile": str(paths["cert"]), "ssl_keyfile": str(paths["key"]), "ssl_ca_certs": str(paths["ca"])}
    signed = ssl.create_default_context(cafile=str(paths["ca"]))
    signed.load_cert_chain(str(paths["client"]))
    cap, timeout = 16, 2.0
    with ThreadServer(service, tls=mutual, max_connections=cap, header_timeout=timeout) as server:
        guard = server.config.guard
        attack = _flood(server.url, 3 * cap, 30.0, "handshake")
        try:
            deadline = time.monotonic() + 20
            while len(guard.open) < cap and time.monotonic() < deadline:  # the silent handshakes fill the cap
                time.sleep(0.05)
            assert len(guard.open) == cap
            times = _good_requests(PlannerClient(server.url, token=TOKEN, ssl_context=signed, timeout=10), 12)
        finally:
            attack.kill()
            attack.wait()
        assert guard.evicted > 0  # counted from their accept: the oldest made room for each newcomer
        assert sorted(times)[len(times) // 2] < timeout / 4, times  # answered, not held behind the handshakes
        with socket.create_connection(("127.0.0.1", server.port)) as silent:  # alone: closed at the timeout
            silent.settimeout(3 * timeout)
            tic = time.monotonic()
            assert silent.recv(100) == b""
            assert 0.8 * timeout < time.monotonic() - tic < 2 * timeout


@pytest.mark.parametrize("http", ["h11", "httptools"])
def test_streamed_and_numerous_headers_are_cut_off_with_either_parser(service, http):
    """Four connections streaming one endless header leave a good client answered at once; each is cut off
    past the head limit (never buffered whole), and a request of too many headers gets 431."""
    if http == "httptools":
        pytest.importorskip("httptools")
    from envs.serve.limits import MAX_HEADER_BYTES, MAX_HEADERS

    with ThreadServer(service, http=http, header_timeout=30.0) as server:
        guard = server.config.guard
        attack = _flood(server.url, 4, 20.0, "headers")
        try:
            deadline = time.monotonic() + 15
            while guard.too_large < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            times = _good_requests(PlannerClient(server.url, token=TOKEN, timeout=10), 12)
        finally:
            attack.kill()
            attack.wait()
        # cut off long before the 30 s header timeout, by size (h11 refuses past its own event size limit first)
        assert guard.too_large >= 4 or (http == "h11" and guard.timed_out == 0), (guard.too_large, guard.timed_out)
        assert sorted(times)[len(times) // 2] < 0.25, times
        many = {f"X-Header-{k}": "1" for k in range(MAX_HEADERS + 1)}
        assert raw(server.url, "GET", "/health", headers=many)[0] == 431
        # a refused head is not acted on, even where its request arrived whole: no stream is opened
        opened = len(server.gateway.streams)
        bearer = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
        assert raw(server.url, "POST", "/streams", b'{"layout": "4way"}', {**bearer, **many})[0] == 431
        time.sleep(0.2)
        assert len(server.gateway.streams) == opened
        assert raw(server.url, "GET", "/health", headers={"X-Big": "a" * (MAX_HEADER_BYTES + 1)})[0] in (400, 431)
        assert raw(server.url, "GET", "/health", headers={f"X-Header-{k}": "1" for k in range(8)})[0] == 200


def test_failed_tokens_are_rate_limited_and_logged_boundedly(service):
    """A burst of wrong tokens from one address: the first ones get 401, the rest 429, a couple of log lines in
    all; the right token from the same address is still served (no lockout of good clients sharing it)."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    logger = logging.getLogger("envs.serve.access")
    logger.addHandler(handler)
    try:
        with ThreadServer(service) as server:
            limit = server.gateway.failures
            wrong = PlannerClient(server.url, token="wrong-token-0123456789")
            statuses = []
            for _ in range(300):
                try:
                    wrong.version()
                except RemotePlannerError as error:
                    statuses.append((error.status, error.field))
            assert PlannerClient(server.url, token=TOKEN).version()["planner"] == "PR"
    finally:
        logger.removeHandler(handler)
    unauthorised = statuses.count((401, "authorization"))
    assert len(statuses) == 300 and unauthorised + statuses.count((429, "authorization")) == 300
    assert int(limit.burst) <= unauthorised < 100 and limit.limited == 300 - unauthorised
    assert 1 <= len(records) <= 3


def test_duplicate_json_keys_are_refused_naming_the_key(service):
    headers = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
    with ThreadServer(service) as server:
        status, reply = raw(server.url, "POST", "/streams", b'{"layout": "4way", "layout": "3way"}', headers)
        assert (status, reply["field"]) == (422, "layout") and "twice" in reply["error"]
        stream = PlannerClient(server.url, token=TOKEN).open("4way")
        body = json.dumps({**wire_scene(2, 0.0, service.builder.layout), "seq": 1})
        twice = body.replace('"speed": 5.0', '"speed": 5.0, "speed": 19.0', 1).encode()
        status, reply = raw(server.url, "POST", f"/streams/{stream}/step", twice, headers)
        assert (status, reply["field"]) == (422, "speed")
        assert raw(server.url, "POST", f"/streams/{stream}/step", body.encode(), headers)[0] == 200


def test_a_symlinked_token_folder_is_refused_and_its_target_left_alone(tmp_path, monkeypatch):
    from envs.commands.serve import _access
    from sb3_graph.cli import UserError

    target = tmp_path / "elsewhere"
    target.mkdir(mode=0o755)
    os.chmod(target, 0o755)
    runtime = tmp_path / "runtime"
    runtime.mkdir()
    (runtime / "sb3-graph").symlink_to(target)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    with pytest.raises(UserError, match="symbolic link"):
        _access(Namespace(allowed_host=[], no_token=False), None, "127.0.0.1", 41234)
    assert stat.S_IMODE(target.stat().st_mode) == 0o755 and not list(target.iterdir())


def test_without_tokens_every_loopback_address_is_one_client():
    from envs.serve.access import Access

    access = Access([], ["localhost"])
    assert access.client(None, "127.0.0.1") == access.client(None, "127.0.0.2") == access.client(None, "::1")
    assert access.client(None, "192.0.2.7") != access.client(None, "127.0.0.1")


def test_a_key_that_does_not_match_its_certificate_stops_the_start_before_serving(tmp_path):
    paths = _certificates(tmp_path)
    other = pytest.importorskip("trustme").CA().issue_cert("127.0.0.1")
    other.private_key_pem.write_to_path(tmp_path / "other.pem")
    command = [sys.executable, "-m", "sb3_graph.cli", "serve", "--planner", "pr", "--port", "0", "--workers", "0",
               "--ssl-certfile", str(paths["cert"]), "--ssl-keyfile", str(tmp_path / "other.pem")]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=180,
                          env={**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)})  # fmt: skip
    assert done.returncode == 2 and "serving" not in done.stdout
    assert "--ssl-certfile/--ssl-keyfile" in done.stderr and "Traceback" not in done.stderr
