"""Where the planner server plans: on its event loop, or in worker processes with stream affinity.

A stream's planner state (AIM's reservations, the shield's plans, signal phases) lives in exactly one
place: :class:`InlinePool` keeps every stream in the server's own process (one decision at a time, as
before ``--workers``); :class:`ProcessPool` gives each stream to one of ``N`` worker processes when it
opens, and sends all its requests there, so that streams on different workers are planned in parallel
and one large scene holds only the streams of its own worker.

A request crosses to a worker as its raw body and comes back as the answer's status and JSON bytes:
the worker parses, checks, plans and encodes (:meth:`envs.serve.app.PlannerService.handle`), so that
this CPU work runs in parallel too. Frames on the socket pair: a 4-byte length and a pickle of a tuple
of plain values (the server talking to its own children; no user data is ever unpickled).
"""

from __future__ import annotations

import asyncio
import itertools
import multiprocessing
import os
import pickle
import signal
import socket
import struct
from typing import Any

_LENGTH = struct.Struct("!I")


class WorkerGone(RuntimeError):
    """A worker process ended (its streams are lost)."""


class InlinePool:
    """Plans on the server's event loop (``--workers 0``): one decision at a time, no time limit.

    :param service: the planners (:class:`envs.serve.app.PlannerService`)
    """

    size = 1

    def __init__(self, service: Any) -> None:
        self.service = service
        self.load = [0]

    async def start(self) -> None:
        pass

    def alive(self, worker: int) -> bool:
        return True

    async def call(self, worker: int, op: str, sid: str, body: bytes, timeout: float | None) -> tuple[int, bytes]:
        return self.service.handle(op, sid, body)

    async def close(self) -> None:
        pass


def _recv(sock: socket.socket) -> Any:
    head = _recv_exactly(sock, _LENGTH.size)
    if head is None:
        return None
    body = _recv_exactly(sock, _LENGTH.unpack(head)[0])
    return None if body is None else pickle.loads(body)


def _recv_exactly(sock: socket.socket, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = sock.recv(min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _frame(value: Any) -> bytes:
    data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    return _LENGTH.pack(len(data)) + data


def _worker_main(sock: socket.socket, service: Any, others: list[socket.socket]) -> None:
    """A worker's loop: requests in, answers out, in order, until the server closes its end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the server, which then closes the socket
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    for other in others:
        other.close()
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    while True:
        message = _recv(sock)
        if message is None:
            return
        request, op, sid, body = message
        try:
            status, payload = service.handle(op, sid, body)
        except Exception as error:  # noqa: BLE001 - a planner's failure answers 500, the worker goes on
            status, payload = 500, f'{{"error": "server: {type(error).__name__}", "field": "server"}}'.encode()
        sock.sendall(_frame((request, status, payload)))


class ProcessPool:
    """``workers`` planning processes (forked from the server once its planner is built and warm).

    :param service: the planners, copied into each worker
    :param workers: number of processes
    """

    def __init__(self, service: Any, workers: int) -> None:
        self.size = int(workers)
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        context = multiprocessing.get_context(method)
        pairs = [socket.socketpair() for _ in range(self.size)]
        self.processes, self.sockets = [], []
        for k, (mine, theirs) in enumerate(pairs):
            # the child keeps only its own end: every server end, and the later pairs' child ends, are closed there
            others = [s for j, (a, b) in enumerate(pairs) for s in ((a, b) if j > k else (a,))]
            process = context.Process(target=_worker_main, args=(theirs, service, others), daemon=True,
                                      name=f"sb3-graph-planner-{k}")  # fmt: skip
            process.start()
            theirs.close()
            self.processes.append(process)
            self.sockets.append(mine)
        self.load = [0] * self.size  # streams per worker (kept by the server)
        self._pending: dict[int, asyncio.Future] = {}
        self._ids = itertools.count()
        self._writers: list[asyncio.StreamWriter | None] = [None] * self.size
        self._readers: list[asyncio.Task] = []
        self._dead = [False] * self.size

    async def start(self) -> None:
        """Connect the sockets to the running event loop (the server's startup)."""
        for k, sock in enumerate(self.sockets):
            sock.setblocking(False)
            reader, writer = await asyncio.open_connection(sock=sock, limit=1 << 26)
            self._writers[k] = writer
            self._readers.append(asyncio.get_running_loop().create_task(self._read(k, reader)))

    async def _read(self, worker: int, reader: asyncio.StreamReader) -> None:
        try:
            while True:
                head = await reader.readexactly(_LENGTH.size)
                request, status, payload = pickle.loads(await reader.readexactly(_LENGTH.unpack(head)[0]))
                future = self._pending.pop(request, None)
                if future is not None and not future.done():
                    future.set_result((status, payload))
        except (asyncio.IncompleteReadError, ConnectionError, OSError):
            self._dead[worker] = True
            for request, future in list(self._pending.items()):
                if getattr(future, "worker", None) == worker and not future.done():
                    self._pending.pop(request, None)
                    future.set_exception(WorkerGone(f"planning process {worker} ended"))

    def alive(self, worker: int) -> bool:
        return not self._dead[worker] and self.processes[worker].is_alive()

    async def call(self, worker: int, op: str, sid: str, body: bytes, timeout: float | None) -> tuple[int, bytes]:
        """One request to ``worker``: its status and JSON answer.

        :raises TimeoutError: no answer within ``timeout`` seconds (the worker still finishes it)
        :raises WorkerGone: the worker ended
        """
        if not self.alive(worker):
            raise WorkerGone(f"planning process {worker} ended")
        request = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        future.worker = worker  # type: ignore[attr-defined]
        self._pending[request] = future
        self._writers[worker].write(_frame((request, op, sid, body)))
        try:
            return await asyncio.wait_for(asyncio.shield(future), timeout)
        except asyncio.TimeoutError:
            self._pending.pop(request, None)
            raise TimeoutError(f"no answer within {timeout} s") from None

    async def close(self) -> None:
        for writer in self._writers:
            if writer is not None:
                writer.close()
        for task in self._readers:
            task.cancel()
        for process in self.processes:
            process.join(timeout=2)
            if process.is_alive():
                os.kill(process.pid, signal.SIGKILL)
