"""A small Python client of the planner server, and the planner that plans through it.

Standard library only (``http.client`` over one kept-alive connection), no ``sb3_graph``::

    from envs.serve.client import PlannerClient

    client = PlannerClient("http://127.0.0.1:8765")
    stream = client.open(layout="4way", seed=0)
    accelerations = client.step(stream, scene_to_wire(env.unwrapped.scene()))
    client.close(stream)

:class:`RemotePlanner` is a :class:`~envs.planners.Planner` whose ``act`` asks the server; it is what
the planner spec ``http://HOST:PORT`` builds in ``evaluate``, ``sweep`` and ``ind``
(``http://HOST:PORT+shield``: shielded here, in the client). The token of a server started with
``--token-file`` is read from the file named by the environment variable :data:`TOKEN_FILE_VARIABLE`.
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import weakref
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from envs.planners.base import Planner
from envs.serve.wire import scene_to_wire
from envs.simulation.scene import Scene

TOKEN_FILE_VARIABLE = "SB3_GRAPH_TOKEN_FILE"
REMOTE_SCHEMES = ("http://",)


class RemotePlannerError(ValueError):
    """The server refused a request or could not be reached.

    :param status: HTTP status (0: no answer)
    :param field: the field the server named (``""`` if none)
    :param message: one line
    """

    def __init__(self, status: int, field: str, message: str) -> None:
        super().__init__(message)
        self.status, self.field = status, field


def parse_address(url: str) -> tuple[str, int]:
    """Host and port of ``http://HOST:PORT`` (no path, query, user or fragment).

    :param url: the address
    :return: ``(host, port)``
    :raises ValueError: anything else, naming the part
    """
    parts = urlsplit(str(url).strip())
    if parts.scheme != "http":
        raise ValueError(f"planner server {url!r}: the address must start with http://")
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username or parts.password:
        raise ValueError(f"planner server {url!r}: give only http://HOST:PORT (no path, query or user)")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"planner server {url!r}: the port must be a number from 1 to 65535") from None
    if not parts.hostname or port is None:
        raise ValueError(f"planner server {url!r}: give both host and port, http://HOST:PORT")
    return parts.hostname, port


def read_token(path: str | Path | None) -> str | None:
    """The token in a file (its first line, stripped), or ``None`` for no file.

    :param path: the token file
    :raises ValueError: an unreadable or empty file
    """
    if path is None:
        return None
    try:
        token = Path(path).read_text(encoding="utf-8").strip().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"token file {str(path)!r} cannot be read ({error})") from None
    if not token or not token[0].strip():
        raise ValueError(f"token file {str(path)!r} is empty")
    return token[0].strip()


class PlannerClient:
    """The planner server's endpoints as methods, over one kept-alive HTTP connection.

    :param url: ``http://HOST:PORT``
    :param token: the server's token (default: read from the file named by ``$SB3_GRAPH_TOKEN_FILE``, if set)
    :param timeout: seconds to wait for an answer
    """

    def __init__(self, url: str, token: str | None = None, timeout: float = 30.0) -> None:
        self.url = str(url).strip().rstrip("/")
        self.host, self.port = parse_address(self.url)
        self.token = token if token is not None else read_token(os.environ.get(TOKEN_FILE_VARIABLE) or None)
        self.timeout = float(timeout)
        self._connection: http.client.HTTPConnection | None = None
        # the server's own time for the last answer [ms] (its Server-Timing header; nan without one)
        self.server_ms = float("nan")
        # the server shield's report of the last step (``None`` for a server without --shield)
        self.last_shield: dict[str, Any] | None = None

    def request(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """One request; its JSON answer.

        :raises RemotePlannerError: a 4xx/5xx answer (with the server's field and message) or no answer
        """
        data = None if body is None else json.dumps(body, allow_nan=False).encode()
        headers = {"Content-Type": "application/json"} if data is not None else {}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        for attempt in (0, 1):  # a kept-alive connection that the server closed is opened once more
            if self._connection is None:
                self._connection = self._connect()
            try:
                self._connection.request(method, path, body=data, headers=headers)
                response = self._connection.getresponse()
                payload = response.read()
                self.server_ms = _server_ms(response.getheader("server-timing"))
                break
            except (ConnectionError, http.client.HTTPException, OSError) as error:
                self.disconnect()
                if attempt or not isinstance(error, (ConnectionResetError, http.client.RemoteDisconnected,
                                                     BrokenPipeError)):  # fmt: skip
                    raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
        if response.status >= 400:
            try:
                reply = json.loads(payload)
                field, message = str(reply.get("field", "")), str(reply.get("error", payload[:200]))
            except (ValueError, AttributeError):
                field, message = "", payload[:200].decode(errors="replace")
            raise RemotePlannerError(response.status, field, f"planner server {self.url}: {response.status} {message}")
        return json.loads(payload) if payload else None

    def _connect(self) -> http.client.HTTPConnection:
        connection = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
        try:
            connection.connect()
        except OSError as error:
            raise RemotePlannerError(0, "", f"planner server {self.url}: no answer ({error})") from None
        # http.client writes the headers and the body in two segments: without this, Nagle's algorithm
        # holds the body until the server acknowledges the headers (a delayed ACK: about 40 ms per request).
        connection.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return connection

    def disconnect(self) -> None:
        """Close the connection (the next request opens a new one)."""
        if self._connection is not None:
            self._connection.close()
            self._connection = None

    def health(self) -> dict[str, Any]:
        return self.request("GET", "/health")

    def version(self) -> dict[str, Any]:
        """What the server runs (planner, layout, policy period, limits)."""
        return self.request("GET", "/version")

    def open(self, layout: str, dt: float | None = None, seed: int | None = None) -> str:
        """Open a stream; its id.

        :param layout: layout name of the scenes that will be sent
        :param dt: the client's policy period [s] (the server refuses another)
        :param seed: seed of the planner
        """
        return self.request("POST", "/streams", {"layout": layout, "dt": dt, "seed": seed})["stream"]

    def step(self, stream: str, scene: dict[str, Any]) -> np.ndarray:
        """One decision.

        :param stream: stream id
        :param scene: the wire scene (:func:`envs.serve.wire.scene_to_wire`)
        :return: ``(n,)`` accelerations [m/s^2], row ``i`` for ``scene["vehicles"][i]``
        :raises RemotePlannerError: a refusal, or an answer for other vehicles
        """
        reply = self.request("POST", f"/streams/{stream}/step", scene)
        ids = [v["id"] for v in scene["vehicles"]]
        if reply.get("ids") != ids or len(reply.get("accelerations", ())) != len(ids):
            raise RemotePlannerError(0, "ids", f"planner server {self.url}: the answer is for other vehicles")
        self.last_shield = reply.get("shield")
        return np.asarray(reply["accelerations"], dtype=float)

    def reset(self, stream: str, seed: int | None = None) -> None:
        """A new episode in the stream."""
        self.request("POST", f"/streams/{stream}/reset", {"seed": seed})

    def close(self, stream: str) -> None:
        """Close a stream (its planner state is dropped)."""
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

    :param url: ``http://HOST:PORT``
    :param token: the server's token (default: from ``$SB3_GRAPH_TOKEN_FILE``)
    :param name: report name (default: ``<server's planner name>@HOST:PORT``)

    Behind a server started with ``--shield`` it keeps the shield's counters (``interventions``,
    ``vehicle_steps``, ``unresolved``) from the server's answers and reports them in :meth:`stats`,
    as a local shield does.
    """

    def __init__(self, url: str, token: str | None = None, name: str | None = None) -> None:
        self.client = PlannerClient(url, token=token)
        self.info = self.client.version()
        super().__init__(name or remote_name(self.info, self.client))
        self.stream: str | None = None
        self._seed: int | None = None
        self._fresh = True
        self._finalizer: weakref.finalize | None = None
        self.shielded = bool(self.info.get("shield"))  # the server shields: its counters, as a local Shield's
        self.interventions = self.vehicle_steps = self.unresolved = 0

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

    def act(self, scene: Scene) -> np.ndarray:
        wire = scene_to_wire(scene)
        if self.stream is None:
            self.stream = self.client.open(wire["layout"], dt=float(scene.dt), seed=self._seed)
            self._finalizer = weakref.finalize(self, _close_quietly, self.client, self.stream)
        elif self._fresh:
            self.client.reset(self.stream, self._seed)
        self._fresh = False
        acc = self.client.step(self.stream, wire)
        report = self.client.last_shield
        if report is not None and self.shielded:
            self.interventions += sum(map(bool, report["overridden"]))
            self.vehicle_steps += len(report["overridden"])
            self.unresolved += bool(report["unresolved"])
        return acc

    def stats(self) -> dict[str, float]:
        """The server's shield's counters of the run (none when the server does not shield).

        The server's answers carry no planner errors: ``planner_errors`` is 0.
        """
        if not self.shielded:
            return {}
        return {
            "shield_interventions": self.interventions,
            "shield_vehicle_steps": self.vehicle_steps,
            "shield_unresolved": self.unresolved,
            "planner_errors": 0,
        }

    def close(self) -> None:
        """Close the stream now."""
        if self._finalizer is not None:
            self._finalizer()
        self.stream = None


def remote_name(info: dict[str, Any], client: PlannerClient) -> str:
    """Report name of a remote planner: ``<planner>@HOST:PORT``."""
    return f"{info['planner']}@{client.host}:{client.port}"
