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

A worker that ends (a crash, or killed by the server because a step overran the time limit) is replaced
by a fresh one built the same way (forked from the server, whose planners are unchanged since they were
built, or sent the pickled service where there is no ``fork``); its streams are lost (their clients get
404 and reopen). At most ``max_restarts`` restarts per slot within ``restart_window`` seconds: past
that the slot stays down (logged once), so that a crash loop cannot spin the CPU.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import itertools
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import stat
import struct
import time
from collections.abc import Callable
from typing import Any

_LENGTH = struct.Struct("!I")
logger = logging.getLogger("envs.serve.workers")


class WorkerGone(RuntimeError):
    """A worker process ended (its streams are lost)."""


class InlinePool:
    """Plans on the server's event loop (``--workers 0``): one decision at a time, no time limit.

    :param service: the planners (:class:`envs.serve.app.PlannerService`)
    """

    size = 1
    restarts = 0
    on_exit: Callable[[int], None] | None = None

    def __init__(self, service: Any) -> None:
        self.service = service
        self.load = [0]
        _freeze()

    def alive_count(self) -> int:
        """Planning processes running (none: the planning is the server's own)."""
        return 0

    async def start(self) -> None:
        pass

    def alive(self, worker: int) -> bool:
        return True

    async def call(self, worker: int, op: str, sid: str, body: bytes, timeout: float | None) -> tuple[int, bytes]:
        return self.service.handle(op, sid, body)

    async def close(self) -> None:
        pass


def _freeze() -> None:
    """Move every object made so far (the planners, built and warm, and the imported modules: about 370,000 with
    AIM behind the shield) out of the collector's reach: a full collection over them takes about 150 ms, a stall
    inside some decision of a long-running server; frozen, it walks only what the decisions make. A forked worker
    inherits the freeze, and does not copy the pages that the collector's walk would have touched."""
    gc.freeze()


def _requests(sock: socket.socket):
    """The requests on a worker's socket, in order, until the server closes it (one ``recv`` usually holds a
    whole request: its length and its pickle)."""
    buffer = bytearray()
    while True:
        while len(buffer) < _LENGTH.size or len(buffer) < _LENGTH.size + _LENGTH.unpack_from(buffer)[0]:
            # 64 KiB: a step fits, and a recv of 1 MiB maps and unmaps its buffer each call (about 10 us more)
            chunk = sock.recv(1 << 16)
            if not chunk:
                return
            buffer += chunk
        end = _LENGTH.size + _LENGTH.unpack_from(buffer)[0]
        message = pickle.loads(bytes(buffer[_LENGTH.size : end]))
        del buffer[:end]
        yield message


def _frame(value: Any) -> bytes:
    data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    return _LENGTH.pack(len(data)) + data


def _drop_sockets(keep: int) -> None:
    """In a forked worker: let go of every socket but ``keep`` (the listening socket, the clients'
    connections, the other workers' pairs), so that a connection the server closes really closes.

    Each is pointed at ``/dev/null`` rather than closed: the number stays taken, so that no object still
    holding it can later close another file that reused it.
    """
    folder = "/proc/self/fd" if os.path.isdir("/proc/self/fd") else "/dev/fd"
    null = os.open(os.devnull, os.O_RDWR)
    try:
        for name in os.listdir(folder):
            fd = int(name)
            if fd in (0, 1, 2, keep, null):
                continue
            try:
                if stat.S_ISSOCK(os.fstat(fd).st_mode):
                    os.dup2(null, fd)
            except OSError:  # the listing's own descriptor, already gone
                continue
    finally:
        os.close(null)


def _worker_main(sock: socket.socket, service: Any, forked: bool) -> None:
    """A worker's loop: requests in, answers out, in order, until the server closes its end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the server, which then closes the socket
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if forked:
        _drop_sockets(sock.fileno())
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    for request, op, sid, body in _requests(sock):
        try:
            status, payload = service.handle(op, sid, body)
        except Exception as error:  # noqa: BLE001 - a planner's failure answers 500, the worker goes on
            status, payload = 500, f'{{"error": "server: {type(error).__name__}", "field": "server"}}'.encode()
        sock.sendall(_frame((request, status, payload)))


class _Answers(asyncio.Protocol):
    """The server's end of a worker's socket: each answer frame resolves its request's future as it arrives (no
    reader task in between).

    :param pending: the futures of the requests sent, by request number (shared with the pool)
    """

    def __init__(self, pending: dict[int, asyncio.Future]) -> None:
        self.pending = pending
        self.buffer = bytearray()
        self.ended = asyncio.get_running_loop().create_future()  # done when the socket closes (the worker ended)

    def data_received(self, data: bytes) -> None:
        buffer = self.buffer
        buffer += data
        while len(buffer) >= _LENGTH.size:
            end = _LENGTH.size + _LENGTH.unpack_from(buffer)[0]
            if len(buffer) < end:
                return
            request, status, payload = pickle.loads(bytes(buffer[_LENGTH.size : end]))
            del buffer[:end]
            future = self.pending.pop(request, None)
            if future is not None and not future.done():
                future.set_result((status, payload))

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.ended.done():
            self.ended.set_result(None)


def _overran(future: asyncio.Future, timeout: float) -> None:
    if not future.done():
        future.set_exception(TimeoutError(f"no answer within {timeout} s"))


class ProcessPool:
    """``workers`` planning processes (forked from the server once its planner is built and warm), each
    replaced when it ends, at most ``max_restarts`` times per slot within ``restart_window`` seconds.

    :param service: the planners, copied into each worker
    :param workers: number of processes
    :param max_restarts: restarts of one slot allowed within ``restart_window``; past them it stays down
    :param restart_window: the window of the restart cap [s]
    """

    def __init__(self, service: Any, workers: int, max_restarts: int = 3, restart_window: float = 60.0) -> None:
        self.size = int(workers)
        self.service = service
        self.max_restarts, self.restart_window = int(max_restarts), float(restart_window)
        self._forked = "fork" in multiprocessing.get_all_start_methods()
        self._context = multiprocessing.get_context("fork" if self._forked else "spawn")
        _freeze()
        self.processes: list[Any] = [None] * self.size
        self.sockets: list[socket.socket | None] = [None] * self.size
        for k in range(self.size):
            self._spawn(k)
        self.load = [0] * self.size  # streams per worker (kept by the server)
        self.restarts = 0  # processes replaced since the start
        self.on_exit: Callable[[int], None] | None = None  # told a slot's worker ended (its streams are lost)
        self._pending: dict[int, asyncio.Future] = {}
        self._ids = itertools.count()
        self._writers: list[asyncio.Transport | None] = [None] * self.size
        self._readers: list[asyncio.Task] = []
        self._dead = [False] * self.size
        self._down = [False] * self.size  # past the restart cap
        self._history = [collections.deque() for _ in range(self.size)]  # restart times per slot
        self._closing = False

    def _spawn(self, worker: int) -> None:
        mine, theirs = socket.socketpair()
        process = self._context.Process(target=_worker_main, args=(theirs, self.service, self._forked),
                                        daemon=True, name=f"sb3-graph-planner-{worker}")  # fmt: skip
        process.start()
        theirs.close()
        self.processes[worker], self.sockets[worker] = process, mine

    async def _connect(self, worker: int) -> None:
        sock = self.sockets[worker]
        sock.setblocking(False)
        loop = asyncio.get_running_loop()
        transport, answers = await loop.create_connection(lambda: _Answers(self._pending), sock=sock)
        self._writers[worker] = transport
        self._readers.append(loop.create_task(self._read(worker, answers)))

    async def start(self) -> None:
        """Connect the sockets to the running event loop (the server's startup)."""
        for k in range(self.size):
            await self._connect(k)

    async def _read(self, worker: int, answers: _Answers) -> None:
        """Wait for the end of ``worker``'s socket (its answers are delivered by ``answers`` as they come), then
        fail its pending requests and replace it."""
        await answers.ended
        self._dead[worker] = True
        for request, future in list(self._pending.items()):
            if getattr(future, "worker", None) == worker and not future.done():
                self._pending.pop(request, None)
                future.set_exception(WorkerGone(f"planning process {worker} ended"))
        if self._closing:
            return
        if self.on_exit is not None:
            self.on_exit(worker)
        await self._restart(worker)

    async def _restart(self, worker: int) -> None:
        """Replace the ended worker of slot ``worker``, unless the slot is past its restart cap."""
        old = self.processes[worker]
        with contextlib.suppress(OSError):
            os.kill(old.pid, signal.SIGKILL)  # it may have only closed its socket
        await asyncio.get_running_loop().run_in_executor(None, old.join, 5.0)
        self._writers[worker].close()
        now = time.monotonic()
        history = self._history[worker]
        while history and now - history[0] > self.restart_window:
            history.popleft()
        if len(history) >= self.max_restarts:
            self._down[worker] = True
            logger.error("planning process %d ended (exit code %s) %d times within %.0f s: not restarted again; "
                         "new streams go to the other workers", worker, old.exitcode, len(history) + 1,
                         self.restart_window)  # fmt: skip
            return
        history.append(now)
        logger.warning("planning process %d ended (exit code %s); its streams are lost; restarting it",
                       worker, old.exitcode)  # fmt: skip
        self._spawn(worker)
        await self._connect(worker)
        self.restarts += 1
        self._dead[worker] = False

    def alive(self, worker: int) -> bool:
        return not self._dead[worker] and self.processes[worker].is_alive()

    def alive_count(self) -> int:
        """Planning processes running now."""
        return sum(self.alive(k) for k in range(self.size))

    def stop(self, worker: int) -> None:
        """Kill ``worker`` (a step overran the time limit): its requests and streams are lost, and the slot
        gets a fresh process."""
        self._dead[worker] = True  # nothing more is sent there, from now
        with contextlib.suppress(OSError):
            os.kill(self.processes[worker].pid, signal.SIGKILL)

    async def call(self, worker: int, op: str, sid: str, body: bytes, timeout: float | None) -> tuple[int, bytes]:
        """One request to ``worker``: its status and JSON answer.

        :raises TimeoutError: no answer within ``timeout`` seconds (the caller may :meth:`stop` the worker)
        :raises WorkerGone: the worker ended
        """
        if self._dead[worker]:  # set by the reader at the worker's end (a dead process closes its socket), or by stop
            raise WorkerGone(f"planning process {worker} ended")
        request = next(self._ids)
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        future.worker = worker  # type: ignore[attr-defined]
        self._pending[request] = future
        self._writers[worker].write(_frame((request, op, sid, body)))
        # A timer on the future itself (asyncio.wait_for and shield would add a task and two futures per request)
        timer = None if timeout is None else loop.call_later(timeout, _overran, future, timeout)
        try:
            return await future
        finally:
            if timer is not None:
                timer.cancel()
            self._pending.pop(request, None)

    async def close(self) -> None:
        self._closing = True
        for writer in self._writers:
            if writer is not None:
                writer.close()
        for task in self._readers:
            task.cancel()
        for process in self.processes:
            process.join(timeout=2)
            if process.is_alive():
                os.kill(process.pid, signal.SIGKILL)
