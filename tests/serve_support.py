"""Helpers of the planner server's tests: a server in a thread of the test process, scenes, a slow planner.

A server in a thread (:class:`ThreadServer`) starts in a fraction of a second, where ``sb3-graph serve``
in its own process takes 10-20 s on the shared machine: the attack tests use it, with the same
uvicorn settings as the command (:func:`envs.serve.app.uvicorn_config`).
"""

from __future__ import annotations

import socket
import threading
import time
from types import SimpleNamespace
from typing import Any

import numpy as np

from envs.planners.base import Planner
from envs.simulation.scene import Scene

TOKEN = "test-token-0123456789"
OTHER_TOKEN = "second-client-token-abcdef"


def serve_extra() -> bool:
    """Whether the ``serve`` extra (FastAPI, uvicorn, msgspec) is installed."""
    try:
        import fastapi  # noqa: F401
        import msgspec  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError:
        return False
    return True


class SlowPlanner(Planner):
    """Brakes every vehicle; takes :attr:`SLOW_SECONDS` for a scene of :attr:`SLOW_VEHICLES` vehicles or more."""

    SLOW_VEHICLES = 5
    SLOW_SECONDS = 1.0

    def __init__(self) -> None:
        super().__init__("Slow")

    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles >= self.SLOW_VEHICLES:
            time.sleep(self.SLOW_SECONDS)
        return np.full(scene.num_vehicles, -1.0)


def wire_scene(n: int, time_s: float, layout: Any) -> dict[str, Any]:
    """A valid wire scene of ``n`` vehicles on successive routes, 10 m apart along them (``n`` <= 12)."""
    vehicles = [{"id": i, "route": layout.route_names[i % layout.num_routes], "arc": 8.0 + 10.0 * i,
                 "speed": 5.0, "length": 4.5, "width": 1.8} for i in range(n)]  # fmt: skip
    return {"layout": layout.name, "time": float(time_s), "captured": time.time(), "vehicles": vehicles}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class ThreadServer:
    """A planner server on ``127.0.0.1:port`` in a thread of this process (a context manager).

    :param service: the planners (:class:`envs.serve.app.PlannerService`)
    :param port: the port (0: a free one)
    :param tokens: accepted tokens (empty: none needed)
    :param hosts: extra ``Host`` names
    :param max_connections: connection cap
    :param header_timeout: header read timeout [s]
    :param body_timeout: body read timeout [s]
    :param tls: uvicorn's ``ssl_*`` settings
    :param http: uvicorn's HTTP implementation (``auto``, ``httptools``, ``h11``)
    :param gateway: :class:`envs.serve.app.Gateway`'s keyword arguments (``workers``, quotas, timeouts)
    """

    def __init__(self, service, port: int = 0, tokens=(TOKEN,), hosts=(), max_connections: int = 64,
                 header_timeout: float = 5.0, body_timeout: float = 10.0, tls: dict | None = None,
                 http: str = "auto", **gateway: Any) -> None:  # fmt: skip
        from envs.serve.access import LOOPBACK_HOSTS, Access
        from envs.serve.app import Gateway

        self.gateway = Gateway(service, Access(list(tokens), [*LOOPBACK_HOSTS, *hosts]), **gateway)
        self.port, self.tls, self.http = port, tls, http
        self.settings = SimpleNamespace(max_connections=max_connections, header_timeout=header_timeout,
                                        body_timeout=body_timeout)  # fmt: skip

    def __enter__(self) -> ThreadServer:
        import uvicorn

        from envs.serve.app import uvicorn_config

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", self.port))
        self.sock.listen(128)
        self.port = self.sock.getsockname()[1]
        s = self.settings
        self.config = uvicorn_config(self.gateway, s.max_connections, s.header_timeout, s.body_timeout, 5.0, self.tls,
                                     self.http)  # fmt: skip
        self.server = uvicorn.Server(self.config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("the server did not start")
            time.sleep(0.02)
        scheme = "https" if self.tls else "http"
        self.url = f"{scheme}://127.0.0.1:{self.port}"
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=20)
        self.sock.close()


def serve_process(*arguments: str, env: dict | None = None, wait: float = 300.0):
    """``sb3-graph serve ARGUMENTS`` in its own process, once it listens: ``(process, url)``."""
    import os
    import select
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, "-m", "sb3_graph.cli", "serve", *arguments]
    process = subprocess.Popen(command, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(root), **(env or {})})  # fmt: skip
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
    raise RuntimeError(f"the server did not start: {process.stderr.read()[-2000:]}")
