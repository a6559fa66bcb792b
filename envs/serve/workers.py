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

A stream's plain WebSocket (the fast path) is handed to its worker after the upgrade (:mod:`envs.serve.handoff`:
its descriptor passed over a second socket pair), which then reads and answers its step frames itself, one
process hop less per step; the server keeps the time limit of those steps by a shared ``[since, key]`` per
worker that it checks on a timer (:meth:`envs.serve.app.Gateway.watch_forever`).

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
import selectors
import signal
import socket
import stat
import struct
import time
from collections.abc import Callable
from typing import Any

from envs.serve.handoff import NORMAL, HandedSocket, close_frame

_LENGTH = struct.Struct("!I")
# A worker's loop turns at least this often [s] (its heartbeat, which the server watches while the worker holds
# handed connections: a worker stopped or stuck outside a step is caught too)
BEAT = 0.05
_SLOT = 3  # shared doubles per worker: since (it began planning a handed connection's step; 0: none), key, heartbeat
logger = logging.getLogger("envs.serve.workers")


class WorkerGone(RuntimeError):
    """A worker process ended (its streams are lost)."""


class InlinePool:
    """Plans on the server's event loop (``--workers 0``): one decision at a time, no time limit.

    :param service: the planners (:class:`envs.serve.app.PlannerService`)
    """

    size = 1
    restarts = 0
    hands = False  # a WebSocket is served on the event loop
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


class _Frames:
    """Length-prefixed pickles read from a stream socket as they arrive (one ``recv`` usually holds a whole
    request: its length and its pickle)."""

    def __init__(self) -> None:
        self.buffer = bytearray()

    def feed(self, chunk: bytes) -> list[Any]:
        buffer = self.buffer
        buffer += chunk
        messages = []
        while len(buffer) >= _LENGTH.size:
            end = _LENGTH.size + _LENGTH.unpack_from(buffer)[0]
            if len(buffer) < end:
                break
            messages.append(pickle.loads(bytes(buffer[_LENGTH.size : end])))
            del buffer[:end]
        return messages


def _frame(value: Any) -> bytes:
    data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    return _LENGTH.pack(len(data)) + data


def _drop_sockets(keep: tuple[int, ...]) -> None:
    """In a forked worker: let go of every socket but ``keep`` (its own pairs; not the listening socket, the
    clients' connections, the other workers' pairs), so that a connection the server closes really closes.

    Each is pointed at ``/dev/null`` rather than closed: the number stays taken, so that no object still
    holding it can later close another file that reused it.
    """
    folder = "/proc/self/fd" if os.path.isdir("/proc/self/fd") else "/dev/fd"
    null = os.open(os.devnull, os.O_RDWR)
    try:
        for name in os.listdir(folder):
            fd = int(name)
            if fd in (0, 1, 2, null) or fd in keep:
                continue
            try:
                if stat.S_ISSOCK(os.fstat(fd).st_mode):
                    os.dup2(null, fd)
            except OSError:  # the listing's own descriptor, already gone
                continue
    finally:
        os.close(null)


class _Worker:
    """A worker's loop: the server's requests in, answers out, and the WebSockets handed to it
    (:mod:`envs.serve.handoff`) read, planned and answered here, until the server closes its end.

    :param sock: the socket pair's end for requests and answers
    :param hand: the socket pair's end on which handed connections arrive (``None``: none are handed)
    :param busy: the pool's shared ``[since, key, heartbeat]`` per worker: when this worker began planning a step
        of a handed connection (0: it plans none), that connection's key, and when its loop last turned, for the
        server's time limit
    :param slot: this worker's index into ``busy`` (``3 * worker``)
    :param service: the planners (:class:`envs.serve.app.PlannerService`)
    """

    def __init__(self, sock: socket.socket, hand: socket.socket | None, busy: Any, slot: int, service: Any) -> None:
        self.sock, self.hand, self.busy, self.slot, self.service = sock, hand, busy, slot, service
        self.selector = selectors.DefaultSelector()
        self.requests, self.hands = _Frames(), _Frames()
        self.fds: collections.deque[int] = collections.deque()  # received with the hand-overs, in order
        self.sockets: dict[str, HandedSocket] = {}  # by stream

    def run(self) -> None:
        self.selector.register(self.sock, selectors.EVENT_READ)
        if self.hand is not None:
            self.selector.register(self.hand, selectors.EVENT_READ)
        beat = self.slot + 2
        while True:
            events_ready = self.selector.select(BEAT)
            self.busy[beat] = time.monotonic()
            for key, events in events_ready:
                target = key.fileobj
                if target is self.sock:
                    chunk = self.sock.recv(1 << 16)  # 64 KiB: a step fits; 1 MiB would map and unmap each call
                    if not chunk:
                        return
                    for request, op, sid, body in self.requests.feed(chunk):
                        self.sock.sendall(_frame((request, *self.answer(op, sid, body))))
                elif target is self.hand:
                    self.received()
                else:
                    self.serve(target, events)

    def answer(self, op: str, sid: str, body: bytes) -> tuple[int, bytes]:
        """A request of the server (a step over HTTP, an open, a close...)."""
        if op == "last_used":  # the stream's last message on its handed connection, for the idle expiry
            handed = self.sockets.get(sid)
            return 200, repr(handed.last_used if handed is not None else 0.0).encode()
        try:
            status, payload = self.service.handle(op, sid, body)
        except Exception as error:  # noqa: BLE001 - a planner's failure answers 500, the worker goes on
            status, payload = 500, f'{{"error": "server: {type(error).__name__}", "field": "server"}}'.encode()
        if op in ("close", "expire"):  # a closed or expired stream keeps no connection
            self.release(sid)
        return status, payload

    def received(self) -> None:
        """Connections handed over (each with its descriptor), or to let go."""
        data, fds, _, _ = socket.recv_fds(self.hand, 1 << 16, 8)
        self.fds.extend(fds)
        if not data:  # the server closed its end: the requests' socket ends too
            self.selector.unregister(self.hand)
            return
        for message in self.hands.feed(data):
            if message[0] == "socket":
                _, key, sid, max_size = message
                handed = HandedSocket(socket.socket(fileno=self.fds.popleft()), key, sid, max_size)
                self.release(sid)  # a new connection replaces the stream's old one
                self.sockets[sid] = handed
                self.selector.register(handed, selectors.EVENT_READ)
            else:  # ("release", key, sid)
                handed = self.sockets.get(message[2])
                if handed is not None and handed.key == message[1]:
                    self.release(message[2])

    def plan(self, handed: HandedSocket, message: bytes, text: bool) -> bytes:
        """The answer frame to a message of a handed connection."""
        from envs.serve import frames

        if text:
            return frames.TEXT_REFUSAL
        busy, slot = self.busy, self.slot
        busy[slot + 1] = handed.key
        busy[slot] = time.monotonic()
        try:
            return self.service.handle("frame", handed.sid, message)[1]
        except Exception as error:  # noqa: BLE001 - a planner's failure answers 500, the worker goes on
            return frames.encode_error(500, "server", f"server: {type(error).__name__}")
        finally:
            busy[slot] = 0.0

    def serve(self, handed: HandedSocket, events: int) -> None:
        """A handed connection is readable or writable: answer its whole messages, send what waits."""
        if self.sockets.get(handed.sid) is not handed:  # released earlier in this turn of the loop
            return
        if events & selectors.EVENT_WRITE:
            handed.flush()
        if events & selectors.EVENT_READ and not handed.read():  # the peer went: nothing more to send
            handed.closed = True
            handed.outbox.clear()
        handed.messages(lambda message, text: self.plan(handed, message, text))
        if handed.closed and not handed.outbox:
            self.release(handed.sid)
            return
        wanted = selectors.EVENT_WRITE if handed.outbox else selectors.EVENT_READ
        if self.selector.get_key(handed).events != wanted:
            self.selector.modify(handed, wanted)

    def release(self, sid: str) -> None:
        """Close the stream's handed connection, if any, and tell the server (which then closes its own end)."""
        handed = self.sockets.pop(sid, None)
        if handed is None:
            return
        if not handed.closed:
            handed.send(close_frame(NORMAL))
        with contextlib.suppress(KeyError, ValueError):
            self.selector.unregister(handed)
        handed.close()
        self.sock.sendall(_frame((-1, "closed", handed.key)))


def _worker_main(sock: socket.socket, hand: socket.socket | None, busy: Any, slot: int, service: Any,
                 forked: bool) -> None:  # fmt: skip
    """A worker process: see :class:`_Worker`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the server, which then closes the socket
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if forked:
        _drop_sockets((sock.fileno(),) + ((hand.fileno(),) if hand is not None else ()))
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    _Worker(sock, hand, busy, slot, service).run()


class _Answers(asyncio.Protocol):
    """The server's end of a worker's socket: each answer frame resolves its request's future as it arrives (no
    reader task in between).

    :param pending: the futures of the requests sent, by request number (shared with the pool)
    :param closed: told the key of each handed connection that the worker closed
    """

    def __init__(self, pending: dict[int, asyncio.Future], closed: Callable[[int], None]) -> None:
        self.pending, self.closed = pending, closed
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
            if request == -1:  # not an answer: a handed connection that the worker closed
                self.closed(payload)
                continue
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
        # a plain WebSocket is handed to its stream's worker where descriptors can be passed (SCM_RIGHTS)
        self.hands = hasattr(socket, "send_fds")
        # per worker [since, key, heartbeat] (see _Worker), for the time limit of the handed connections' steps
        self.busy = self._context.RawArray("d", _SLOT * self.size)
        _freeze()
        self.processes: list[Any] = [None] * self.size
        self.sockets: list[socket.socket | None] = [None] * self.size
        self.hand_sockets: list[socket.socket | None] = [None] * self.size
        for k in range(self.size):
            self._spawn(k)
        self.load = [0] * self.size  # streams per worker (kept by the server)
        self.restarts = 0  # processes replaced since the start
        self.on_exit: Callable[[int], None] | None = None  # told a slot's worker ended (its streams are lost)
        self.on_closed: Callable[[int], None] = lambda key: None  # told a worker closed a handed connection
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
        hand = theirs_hand = None
        if self.hands:
            hand, theirs_hand = socket.socketpair()
            hand.setblocking(False)  # a hand-over that does not fit now is served on the event loop instead
        self.busy[_SLOT * worker] = 0.0
        self.busy[_SLOT * worker + 2] = time.monotonic() + 60.0  # time to start (spawned: import) before a first beat
        process = self._context.Process(target=_worker_main, daemon=True, name=f"sb3-graph-planner-{worker}",
                                        args=(theirs, theirs_hand, self.busy, _SLOT * worker, self.service,
                                              self._forked))  # fmt: skip
        process.start()
        theirs.close()
        if theirs_hand is not None:
            theirs_hand.close()
        if self.hand_sockets[worker] is not None:
            self.hand_sockets[worker].close()
        self.processes[worker], self.sockets[worker], self.hand_sockets[worker] = process, mine, hand

    async def _connect(self, worker: int) -> None:
        sock = self.sockets[worker]
        sock.setblocking(False)
        loop = asyncio.get_running_loop()
        transport, answers = await loop.create_connection(lambda: _Answers(self._pending, self._closed), sock=sock)
        self._writers[worker] = transport
        self._readers.append(loop.create_task(self._read(worker, answers)))

    def _closed(self, key: int) -> None:
        self.on_closed(key)

    def hand(self, worker: int, key: int, sid: str, fd: int, max_size: int) -> bool:
        """Pass a WebSocket's descriptor ``fd`` (a duplicate: the caller closes its own) to ``worker``, which from
        then on serves stream ``sid``'s steps on it; ``False`` if it could not (serve it on the event loop)."""
        hand = self.hand_sockets[worker]
        if hand is None or not self.alive(worker):
            return False
        try:
            socket.send_fds(hand, [_frame(("socket", key, sid, max_size))], [fd])
        except OSError:  # BlockingIOError: the worker has not read its hand-overs for a long while
            return False
        return True

    def release(self, worker: int, key: int, sid: str) -> None:
        """Ask ``worker`` to close the handed connection ``key`` of stream ``sid`` (with a close frame)."""
        hand = self.hand_sockets[worker]
        if hand is not None and self.alive(worker):
            with contextlib.suppress(OSError):
                hand.send(_frame(("release", key, sid)))

    def planning(self, worker: int) -> tuple[float, int]:
        """Since when ``worker`` plans a step of a handed connection (``time.monotonic``; 0: it plans none), and
        that connection's key."""
        return self.busy[_SLOT * worker], int(self.busy[_SLOT * worker + 1])

    def heartbeat(self, worker: int) -> float:
        """When ``worker``'s loop last turned (``time.monotonic``; it turns at least every :data:`BEAT` seconds
        while it does not plan)."""
        return self.busy[_SLOT * worker + 2]

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
        for hand in self.hand_sockets:
            if hand is not None:
                hand.close()
        for task in self._readers:
            task.cancel()
        for process in self.processes:
            process.join(timeout=2)
            if process.is_alive():
                os.kill(process.pid, signal.SIGKILL)
