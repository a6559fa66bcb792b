"""A small Python client of the planner server, and the planner that plans through it.

The standard library and numpy (``http.client`` over one kept-alive connection; with ``msgspec``, the fast path:
one WebSocket per stream, :mod:`envs.serve.websocket`, with binary frames, :mod:`envs.serve.frames`), no
``sb3_graph``::

    from envs.serve.client import PlannerClient

    client = PlannerClient("http://127.0.0.1:8765")
    stream = client.open(layout="4way", seed=0)
    accelerations = client.step(stream, scene_to_wire(env.unwrapped.scene()))
    client.close(stream)

:class:`RemotePlanner` is a :class:`~envs.planners.Planner` whose ``act`` asks the server; it is what
the planner spec ``http://HOST:PORT`` (or ``https://``) builds in ``evaluate``, ``sweep`` and ``ind``
(``http://HOST:PORT+shield``: :class:`RemoteShield`, shielded here, in the client). It survives the
server: every decision has a deadline (one policy period by default, ``$SB3_GRAPH_DEADLINE`` seconds
otherwise), within which it retries with capped exponential backoff and reopens a stream the server
lost (a restart), sending this decision's scene to the new stream; a decision that misses its deadline
gets the vehicle-side fallback and is counted (``remote_deadline_misses`` in ``metrics.csv``).

The token: ``token=``, else the first token of the file named by :data:`TOKEN_FILE_VARIABLE`, else the
token file that a server on this machine wrote for its address (:func:`envs.serve.access.default_token_path`).
TLS (``https://``): the server's certificate is checked against :data:`CA_FILE_VARIABLE`'s bundle (else
the system's), and :data:`CLIENT_CERT_VARIABLE` / :data:`CLIENT_KEY_VARIABLE` name a client certificate
for a server that asks for one (mutual TLS).
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import ssl
import time
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from envs.planners.base import Planner
from envs.planners.loading import parse_url
from envs.planners.shield import Shield
from envs.serve.access import default_token_path, read_tokens
from envs.serve.websocket import UpgradeRefused, WebSocket
from envs.serve.wire import scene_to_wire
from envs.simulation import hooks
from envs.simulation.scene import Scene

try:  # the fast path's codec (the serve extra); without it the client speaks JSON over HTTP
    from envs.serve import frames
except ImportError:  # pragma: no cover - msgspec missing
    frames = None  # type: ignore[assignment]

TOKEN_FILE_VARIABLE = "SB3_GRAPH_TOKEN_FILE"
CA_FILE_VARIABLE = "SB3_GRAPH_CA_FILE"
CLIENT_CERT_VARIABLE = "SB3_GRAPH_CLIENT_CERT"
CLIENT_KEY_VARIABLE = "SB3_GRAPH_CLIENT_KEY"
DEADLINE_VARIABLE = "SB3_GRAPH_DEADLINE"
REMOTE_SCHEMES = ("http://", "https://")
# Statuses worth another try within the deadline: no answer, a token the server no longer takes (a restart with
# a new token: the file is read again), too many failures or streams, over the time limit, the server busy.
TRANSIENT = frozenset({0, 401, 429, 502, 503, 504})


class _NoSocket(Exception):
    """The fast path is not available for this step (it goes over HTTP)."""


class RemotePlannerError(ValueError):
    """The server refused a request or could not be reached.

    :param status: HTTP status (0: no answer)
    :param field: the field the server named (``""`` if none)
    :param message: one line
    :param reply: the server's JSON answer (``{}`` if none)
    """

    def __init__(self, status: int, field: str, message: str, reply: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.status, self.field, self.reply = status, field, reply or {}


class DeadlineMissed(RemotePlannerError):
    """No answer within the decision's deadline."""


def parse_address(url: str) -> tuple[str, int]:
    """Host and port of ``http(s)://HOST:PORT`` (see :func:`parse_url`)."""
    return parse_url(url)[1:]


def read_token(path: str | Path | None) -> str | None:
    """The first token in a token file, or ``None`` for no file.

    :param path: the token file
    :raises ValueError: an unreadable or empty file
    """
    if path is None:
        return None
    try:
        return read_tokens(path)[0]
    except ValueError as error:
        if "shorter than 16" in str(error):  # a client's file may hold a short token of its own server's choosing
            return Path(path).read_text(encoding="utf-8").split()[0]
        raise


def _tls_context() -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=os.environ.get(CA_FILE_VARIABLE) or None)
    cert = os.environ.get(CLIENT_CERT_VARIABLE)
    if cert:
        context.load_cert_chain(cert, os.environ.get(CLIENT_KEY_VARIABLE) or None)
    return context


class PlannerClient:
    """The planner server's endpoints as methods, over one kept-alive HTTP connection.

    Steps carry their sequence number (kept here per stream): a step retried after a lost connection
    is answered from the server's cache, never planned twice.

    :param url: ``http://HOST:PORT`` or ``https://HOST:PORT``
    :param token: the server's token (default: :data:`TOKEN_FILE_VARIABLE`'s file, else the server's own
        token file on this machine)
    :param timeout: seconds to wait for an answer
    :param ssl_context: TLS settings of an ``https://`` server (default: from the environment variables)
    :param fast: steps of :meth:`step_scene` over a WebSocket per stream with binary frames (default: when
        ``msgspec`` is installed; HTTP and JSON otherwise, and whenever the server refuses the upgrade)
    """

    def __init__(self, url: str, token: str | None = None, timeout: float = 30.0,
                 ssl_context: ssl.SSLContext | None = None, fast: bool | None = None) -> None:  # fmt: skip
        self.url = str(url).strip().rstrip("/")
        self.scheme, self.host, self.port = parse_url(self.url)
        self._token_file: Path | None = None
        if token is None:
            named = os.environ.get(TOKEN_FILE_VARIABLE) or None
            local = default_token_path(self.host, self.port)
            self._token_file = Path(named) if named else (local if local.is_file() else None)
            token = read_token(self._token_file)
        self.token = token
        self.timeout = float(timeout)
        self.ssl_context = ssl_context if ssl_context is not None or self.scheme == "http" else _tls_context()
        self._connection: http.client.HTTPConnection | None = None
        self._sockets: dict[str, WebSocket] = {}  # the fast path: one WebSocket per stream
        # steps over WebSockets with binary frames when msgspec is installed (the serve extra), else JSON over HTTP
        self.fast = frames is not None if fast is None else bool(fast) and frames is not None
        self.seq: dict[str, int] = {}  # last answered step per stream
        # the server's own time for the last answer [ms] (its Server-Timing header; nan without one)
        self.server_ms = float("nan")
        # the server shield's report of the last step (``None`` for a server without --shield)
        self.last_shield: dict[str, Any] | None = None
        self.last_search: dict[str, Any] | None = None

    def request(self, method: str, path: str, body: dict[str, Any] | bytes | None = None,
                timeout: float | None = None) -> Any:  # fmt: skip
        """One request; its JSON answer. A kept-alive connection that the server closed is reopened once, and a
        token read from a file is read again once on a ``401`` (a restarted server wrote a new one): each
        recovery has its own try, so a stale connection cannot use up the token's.

        :param timeout: seconds for this request (default: the client's)
        :raises RemotePlannerError: a 4xx/5xx answer (with the server's field and message) or no answer
        """
        data = body if isinstance(body, bytes) or body is None else json.dumps(body, allow_nan=False).encode()
        reconnected = reread = False
        while True:
            headers = {"Content-Type": "application/json"} if data is not None else {}
            if self.token:
                headers["Authorization"] = f"Bearer {self.token}"
            fresh = self._connection is None
            try:
                if self._connection is None:
                    self._connection = self._connect(timeout)
                self._connection.sock.settimeout(self.timeout if timeout is None else max(timeout, 1e-3))
                self._connection.request(method, path, body=data, headers=headers)
                response = self._connection.getresponse()
                payload = response.read()
                self.server_ms = _server_ms(response.getheader("server-timing"))
            except (ConnectionError, http.client.HTTPException, OSError) as error:
                self.disconnect()
                stale = isinstance(error, (ConnectionResetError, http.client.RemoteDisconnected, BrokenPipeError))
                if fresh or reconnected or not stale:
                    raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
                reconnected = True  # the server closed the kept-alive connection (an idle timeout, a restart)
                continue
            if response.status == 401 and not reread and self._reread_token():
                reread = True
                continue  # the server restarted with a new token in the same file
            break
        if response.status >= 400:
            try:
                reply = json.loads(payload)
                field, message = str(reply.get("field", "")), str(reply.get("error", payload[:200]))
            except (ValueError, AttributeError):
                reply, field, message = {}, "", payload[:200].decode(errors="replace")
            raise RemotePlannerError(response.status, field, f"planner server {self.url}: {response.status} {message}",
                                     reply if isinstance(reply, dict) else {})  # fmt: skip
        return json.loads(payload) if payload else None

    def _reread_token(self) -> bool:
        if self._token_file is None:
            return False
        try:
            token = read_token(self._token_file)
        except ValueError:
            return False
        changed, self.token = token != self.token, token
        return changed

    def _connect(self, timeout: float | None = None) -> http.client.HTTPConnection:
        seconds = self.timeout if timeout is None else max(timeout, 1e-3)
        if self.scheme == "https":
            connection = http.client.HTTPSConnection(self.host, self.port, timeout=seconds, context=self.ssl_context)
        else:
            connection = http.client.HTTPConnection(self.host, self.port, timeout=seconds)
        try:
            connection.connect()
        except (OSError, ssl.SSLError) as error:
            raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
        # http.client writes the headers and the body in two segments: without this, Nagle's algorithm
        # holds the body until the server acknowledges the headers (a delayed ACK: about 40 ms per request).
        connection.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return connection

    def disconnect(self) -> None:
        """Close the connection and the streams' WebSockets (the next request opens new ones)."""
        if self._connection is not None:
            self._connection.close()
            self._connection = None
        for stream in list(self._sockets):
            self.close_socket(stream)

    def health(self) -> dict[str, Any]:
        return self.request("GET", "/health")

    def version(self) -> dict[str, Any]:
        """What the server runs (planner, layout, policy period, limits)."""
        return self.request("GET", "/version")

    def open(self, layout: str, dt: float | None = None, seed: int | None = None, timeout: float | None = None) -> str:
        """Open a stream; its id.

        :param layout: layout name of the scenes that will be sent
        :param dt: the client's policy period [s] (the server refuses another)
        :param seed: seed of the planner
        """
        stream = self.request("POST", "/streams", {"layout": layout, "dt": dt, "seed": seed}, timeout)["stream"]
        self.seq[stream] = 0
        return stream

    def step(self, stream: str, scene: dict[str, Any], timeout: float | None = None) -> np.ndarray:
        """One decision over HTTP (JSON), planned once however often it is sent: a step with this stream's next
        sequence number, sent again with the same number (and bytes) until answered or ``timeout``.

        :param stream: stream id
        :param scene: the wire scene (:func:`envs.serve.wire.scene_to_wire`)
        :return: ``(n,)`` accelerations [m/s^2], row ``i`` for ``scene["vehicles"][i]``
        :raises RemotePlannerError: a refusal, or an answer for other vehicles
        """
        ids = [v["id"] for v in scene["vehicles"]]

        def send(seq: int) -> dict[str, Any]:
            return self.request("POST", f"/streams/{stream}/step", {**scene, "seq": seq}, timeout)

        reply = self._numbered(stream, send)
        if reply.get("ids") != ids or len(reply.get("accelerations", ())) != len(ids):
            raise RemotePlannerError(0, "ids", f"planner server {self.url}: the answer is for other vehicles")
        self.last_shield = reply.get("shield")
        self.last_search = reply.get("search")  # a lookahead's searches beside the steps (None for other planners)
        return np.asarray(reply["accelerations"], dtype=float)

    def step_scene(self, stream: str, scene: Scene, timeout: float | None = None) -> np.ndarray:
        """One decision for an in-process scene: over the stream's WebSocket with binary frames (the fast path,
        :mod:`envs.serve.frames`) when it can, else as :meth:`step` over HTTP. Exactly once either way: a
        retry carries the same ``seq`` and the same content, whichever path carries it.

        :param stream: stream id
        :param scene: a scene made by the simulation (it needs ``layout`` and ``arc``)
        :return: ``(n,)`` accelerations [m/s^2]
        :raises RemotePlannerError: a refusal, no answer, or an answer for other vehicles
        """
        if not self.fast:
            return self.step(stream, scene_to_wire(scene), timeout)
        if scene.layout is None or scene.arc is None:
            raise ValueError("a remote planner needs scenes with layout and arc (scenes made by the simulation)")
        n = scene.num_vehicles
        width = scene.width if scene.width is not None else np.full(n, 2.0)
        # captured now, once: a retry carries the same time
        columns = (scene.layout.name, float(scene.time), scene.route_names, scene.vehicle_id, scene.route,
                   scene.arc, scene.speed, scene.length, width, time.time())  # fmt: skip

        def send(seq: int) -> dict[str, Any] | None:
            return self._frame_step(stream, frames.encode_step(seq, *columns), timeout)

        try:
            reply = self._numbered(stream, send)
        except _NoSocket:  # no fast path to this stream now: this decision goes over HTTP
            return self.step(stream, scene_to_wire(scene), timeout)
        if not np.array_equal(reply["ids"], scene.vehicle_id) or reply["accelerations"].shape != (n,):
            raise RemotePlannerError(0, "ids", f"planner server {self.url}: the answer is for other vehicles")
        self.server_ms = float("nan")  # no Server-Timing on the fast path
        shield = reply["shield"]
        self.last_shield = None if shield is None else {"overridden": shield["overridden"].tolist(),
                                                        "unresolved": shield["unresolved"]}  # fmt: skip
        return np.array(reply["accelerations"], dtype=float)

    def _numbered(self, stream: str, send) -> dict[str, Any]:
        """``send(seq)`` with the stream's next number; after a 409 naming another expected number (a step of ours
        whose answer never came was planned after all), once more with that one."""
        seq = self.seq.get(stream, 0) + 1
        try:
            reply = send(seq)
        except RemotePlannerError as error:
            expected = error.reply.get("expected") if error.status == 409 and error.field == "seq" else None
            if not isinstance(expected, int) or expected == seq:
                raise
            self.seq[stream] = expected - 1
            reply = send(expected)
        self.seq[stream] = int(reply.get("seq", seq))
        return reply

    def _frame_step(self, stream: str, frame: bytes, timeout: float | None) -> dict[str, Any]:
        """One step frame over the stream's WebSocket (opened on first use); its answer frame, decoded.

        :raises _NoSocket: the upgrade was refused (a stale token or a lost stream: HTTP tells which; a server
            without the fast path: HTTP from now on)
        :raises RemotePlannerError: a refusal frame, or no answer (status 0; the socket is dropped)
        """
        seconds = self.timeout if timeout is None else max(timeout, 1e-3)
        ws = self._sockets.get(stream)
        if ws is None:
            headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
            context = self.ssl_context if self.scheme == "https" else None
            try:
                ws = WebSocket.connect(self.host, self.port, f"/streams/{stream}/ws", headers, seconds, context)
            except UpgradeRefused as error:
                if error.status != 403:  # no WebSocket route on this server: HTTP only
                    self.fast = False
                raise _NoSocket() from None
            except (OSError, ssl.SSLError) as error:
                raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
            self._sockets[stream] = ws
        try:
            ws.send(frame, seconds)
            data = ws.recv(seconds)
        except (OSError, ConnectionError) as error:
            self.close_socket(stream)
            raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
        try:
            reply = frames.decode_reply(data)
        except ValueError as error:
            self.close_socket(stream)
            raise RemotePlannerError(0, "", f"planner server {self.url}: {error}") from None
        if reply["status"] != 200:
            status = int(reply["status"])
            raise RemotePlannerError(status, reply["field"], f"planner server {self.url}: {status} {reply['error']}",
                                     reply)  # fmt: skip
        return reply

    def close_socket(self, stream: str) -> None:
        """Close the stream's WebSocket, if open (the next step opens another)."""
        ws = self._sockets.pop(stream, None)
        if ws is not None:
            ws.close()

    def reset(self, stream: str, seed: int | None = None, timeout: float | None = None) -> None:
        """A new episode in the stream (the sequence numbers start over)."""
        self.request("POST", f"/streams/{stream}/reset", {"seed": seed}, timeout)
        self.seq[stream] = 0

    def close(self, stream: str) -> None:
        """Close a stream (its planner state is dropped)."""
        self.seq.pop(stream, None)
        self.close_socket(stream)
        self.request("DELETE", f"/streams/{stream}")


def _server_ms(header: str | None) -> float:
    """``app;dur=1.234`` -> 1.234 (``nan`` for a missing or other header)."""
    try:
        return float(str(header).split("dur=")[1].split(",")[0].split(";")[0])
    except (IndexError, ValueError):
        return float("nan")


def _close_quietly(client: PlannerClient, stream: str) -> None:
    try:
        client.close(stream)
    except (RemotePlannerError, OSError):
        pass  # the server is gone or has expired the stream already
    client.disconnect()


class RemotePlanner(Planner):
    """A planner that asks a planner server: one stream per planner object, a new episode at each ``reset``.

    The stream opens at the first ``act`` (it needs the scene's layout) and closes when the planner
    is garbage-collected or the process exits; an abandoned stream also expires on the server.

    Each decision has a deadline (``deadline`` seconds, default one policy period, the scene's ``dt``).
    Within it, a request without an answer (no connection, a reset, the server's 503) is sent again
    after a capped exponential backoff (the step with the same sequence number: planned once), and a
    stream the server no longer knows (404: a restart, an expiry) is opened again with the same seed and
    sent this decision's scene. A decision that misses its deadline gets the fallback: every vehicle
    brakes at ``a_min`` (the shield's own last resort), or, behind ``+shield``
    (:class:`RemoteShield`), the shield's fallback command. Refusals of the scene itself (4xx) still
    raise :class:`RemotePlannerError`: they are a bug, not an outage.

    :param url: ``http://HOST:PORT`` or ``https://HOST:PORT``
    :param token: the server's token (default: see :class:`PlannerClient`)
    :param name: report name (default: ``<server's planner name>@HOST:PORT``)
    :param deadline: seconds per decision (default: ``$SB3_GRAPH_DEADLINE``, else the scene's ``dt``)
    :param backoff: first wait before a retry [s]; it doubles up to ``backoff_cap``
    :param backoff_cap: longest wait between retries [s]

    Behind a server started with ``--shield`` it keeps the shield's counters (``interventions``,
    ``vehicle_steps``, ``unresolved``) from the server's answers and reports them in :meth:`stats`,
    as a local shield does; it always reports its own (:meth:`remote_stats`).
    """

    def __init__(
        self,
        url: str,
        token: str | None = None,
        name: str | None = None,
        deadline: float | None = None,
        backoff: float = 0.005,
        backoff_cap: float = 0.05,
    ) -> None:
        self.client = PlannerClient(url, token=token)
        self.info = self.client.version()
        super().__init__(name or remote_name(self.info, self.client))
        self.deadline = _deadline(deadline)
        self.backoff, self.backoff_cap = float(backoff), float(backoff_cap)
        self.raise_on_miss = False  # RemoteShield answers a miss itself
        self.stream: str | None = None
        self._seed: int | None = None
        self._fresh = True
        self._finalizer: weakref.finalize | None = None
        self.shielded = bool(self.info.get("shield"))  # the server shields: its counters, as a local Shield's
        self.interventions = self.vehicle_steps = self.unresolved = 0
        self.deadline_misses = self.retries = self.reopened = 0

    def check_capacity(self, max_vehicles: int, source: str = "planner") -> None:
        """Refuse an environment whose scenes can hold more vehicles than the server takes.

        :raises ValueError: naming the server's ``max_vehicles``
        """
        if int(self.info["max_vehicles"]) < max_vehicles:
            raise ValueError(
                f"{source}: the server takes scenes of at most {self.info['max_vehicles']} vehicles, the environment "
                f"up to max_vehicles={max_vehicles}; start the server with the same --env and --env-kwargs"
            )

    def reset(self, seed: int | None = None) -> None:
        self._seed, self._fresh = seed, True
        self.interventions = self.vehicle_steps = self.unresolved = 0
        self.deadline_misses = self.retries = self.reopened = 0

    def act(self, scene: Scene) -> np.ndarray:
        if scene.layout is None or scene.arc is None:
            raise ValueError("a remote planner needs scenes with layout and arc (scenes made by the simulation)")
        deadline = time.monotonic() + (self.deadline if self.deadline is not None else float(scene.dt))
        try:
            acc = self._decide(scene, deadline)
        except DeadlineMissed:
            self.deadline_misses += 1
            if self.raise_on_miss:
                raise
            return np.full(scene.num_vehicles, float(scene.a_min))
        report = self.client.last_shield
        if report is not None and self.shielded:
            self.interventions += sum(map(bool, report["overridden"]))
            self.vehicle_steps += len(report["overridden"])
            self.unresolved += bool(report["unresolved"])
        return acc

    def _decide(self, scene: Scene, deadline: float) -> np.ndarray:
        """The server's answer to this scene before ``deadline``, retrying what an outage interrupted (no
        answer, a restart with a new token, a lost stream, a busy server); never raises for an outage."""
        wait = self.backoff
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeadlineMissed(0, "", f"planner server {self.client.url}: no answer within the deadline")
            try:
                if self.stream is None:
                    self.stream = self.client.open(scene.layout.name, dt=float(scene.dt), seed=self._seed, timeout=left)
                    self._fresh = False
                    if self._finalizer is not None:
                        self._finalizer.detach()
                    self._finalizer = weakref.finalize(self, _close_quietly, self.client, self.stream)
                elif self._fresh:
                    self.client.reset(self.stream, self._seed, timeout=left)
                    self._fresh = False
                return self.client.step_scene(self.stream, scene, timeout=left)
            except RemotePlannerError as error:
                if error.status == 404 and error.field == "stream":  # the server lost the stream: a new one
                    self.client.close_socket(self.stream)
                    self.stream = None
                    self.reopened += 1
                    continue
                if error.status not in TRANSIENT:
                    raise
            self.retries += 1
            time.sleep(max(0.0, min(wait, deadline - time.monotonic())))
            wait = min(2 * wait, self.backoff_cap)

    def remote_stats(self) -> dict[str, float]:
        """The client's own counters of the run: decisions that missed their deadline (and got the fallback),
        requests sent again, streams opened again."""
        return {"remote_deadline_misses": self.deadline_misses, "remote_retries": self.retries,
                "remote_reopened": self.reopened}  # fmt: skip

    def stats(self) -> dict[str, float]:
        """The client's counters (:meth:`remote_stats`) and the server's shield's (when the server shields).

        The server's answers carry no planner errors: ``planner_errors`` is 0.
        """
        if not self.shielded:
            return self.remote_stats()
        return {
            "shield_interventions": self.interventions,
            "shield_vehicle_steps": self.vehicle_steps,
            "shield_unresolved": self.unresolved,
            "planner_errors": 0,
            **self.remote_stats(),
        }

    def close(self) -> None:
        """Close the stream now."""
        if self._finalizer is not None:
            self._finalizer()
        self.stream = None


class RemoteShield(Shield):
    """The shield in the client around a :class:`RemotePlanner` (``http://HOST:PORT+shield``): a decision
    that misses its deadline gets the shield's fallback command for every vehicle
    (:meth:`~envs.planners.shield.Shield.check` with every vehicle forced), counted as interventions and
    in ``remote_deadline_misses``.

    :param planner: the remote planner
    :param kwargs: :class:`~envs.planners.shield.Shield`'s settings
    """

    def __init__(self, planner: RemotePlanner, **kwargs: Any) -> None:
        super().__init__(planner, **kwargs)
        planner.raise_on_miss = True

    def act(self, scene: Scene) -> np.ndarray:
        try:
            return super().act(scene)
        except DeadlineMissed:
            n = scene.num_vehicles
            return self.check(scene, np.zeros(n), forced=np.ones(n, bool))

    def stats(self) -> dict[str, float]:
        """The shield's counters and the remote planner's own (:meth:`RemotePlanner.remote_stats`)."""
        return {**super().stats(), **self.planner.remote_stats()}


def _deadline(value: float | None) -> float | None:
    """The deadline per decision: ``value``, else ``$SB3_GRAPH_DEADLINE``, else ``None`` (one policy period)."""
    if value is None:
        text = os.environ.get(DEADLINE_VARIABLE, "").strip()
        if not text:
            return None
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"${DEADLINE_VARIABLE} must be a number of seconds, got {text!r}") from None
    if not value > 0:
        raise ValueError(f"the deadline per decision must be > 0 s, got {value}")
    return float(value)


def remote_name(info: dict[str, Any], client: PlannerClient) -> str:
    """Report name of a remote planner: ``<planner>@HOST:PORT``."""
    return f"{info['planner']}@{client.host}:{client.port}"


def make_remote_planner(address: str, shielded: bool = False) -> Planner:
    """The planner that plans through the server at ``address`` (:class:`RemotePlanner`), registered
    for :func:`envs.planners.loading.make_remote_planner`.

    :param address: ``http://HOST:PORT``, normalised
    :param shielded: shield it here, in the client (:class:`RemoteShield`: a missed deadline gets the
        shield's fallback)
    :raises ValueError: the server cannot be reached or refuses (a wrong token)
    """
    planner = RemotePlanner(address)
    return RemoteShield(planner) if shielded else planner


def remote_planner_name(address: str) -> str:
    """Report name of a remote planner, asked from the server: ``<its planner's name>@HOST:PORT``,
    registered for :func:`envs.planners.loading.remote_planner_name`.

    :param address: ``http://HOST:PORT``, normalised
    :raises ValueError: the server cannot be reached or refuses
    """
    client = PlannerClient(address)
    try:
        return remote_name(client.version(), client)
    finally:
        client.disconnect()


# Planner words ``http://HOST:PORT`` build these (envs.planners.loading asks envs.simulation.hooks).
hooks.register("remote_planner", make_remote_planner)
hooks.register("remote_planner_name", remote_planner_name)
