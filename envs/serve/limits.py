"""Connection limits of the planner server, and logging that an attack cannot turn into a full disk.

uvicorn closes an idle kept-alive connection after ``timeout_keep_alive`` and answers 503 above
``limit_concurrency``, but it has no limit on connections at accept, no timeout for a request whose
headers or body never finish arriving (it arms its keep-alive timer only after a response), a TLS
handshake that may take 60 s and is seen only once done, and, with httptools, no limit on a request's
header size. :func:`guarded_protocol` wraps uvicorn's HTTP protocol class so that

- every connection counts from its accept, before any TLS handshake (the server does the handshake itself,
  :meth:`asyncio.loop.start_tls`, instead of handing the certificate to uvicorn);
- at most ``max_connections`` connections are open: a new one over the cap closes the oldest connection
  that has never completed a request (a half-open one, or one still in its handshake), or itself when
  every open connection has;
- the handshake and a request's headers must arrive within ``header_timeout`` seconds of the accept (of
  the request's first byte on a kept-alive connection), and its body within ``body_timeout`` seconds
  more: a sweep every quarter second closes the connections that are late;
- a request's head (request line and headers) holds at most ``max_header_bytes`` bytes and
  ``max_headers`` headers, whichever parser reads it (``431``, then the connection closes);
- a connection upgraded to a WebSocket (:func:`guarded_websocket`) stays counted until it closes.

:class:`RateLimitFilter` keeps the server's log to a bounded rate, and drops the tracebacks that
the event loop attaches to a failed ``accept``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import ssl
import time
from asyncio import sslproto
from typing import Any

# The listening socket's backlog. asyncio accepts up to ``backlog`` connections in one go, and an evicted
# connection's descriptor closes only a few loop iterations later, so a flood can hold about three bursts
# over the cap: 3 x 16 stays inside the 64 descriptors the server keeps in reserve (``RESERVED_FDS``).
ACCEPT_BURST = 16
# uvicorn's HTTP parsers that the server may be told to use (``serve --http``); ``auto``: httptools when installed
HTTP_PARSERS = ("auto", "httptools", "h11")
# A request's head: at most this many bytes (request line and headers) and headers. Enough for any client of
# the server (a step's head is about 200 bytes), small enough that a connection streaming headers costs nothing.
MAX_HEADER_BYTES = 16 * 1024
MAX_HEADERS = 64
# The ASGI scope extension that holds a WebSocket's protocol object (:func:`guarded_websocket`), for the hand-over
CONNECTION = "sb3_graph.connection"


class ConnectionGuard:
    """The open connections of one server, their caps and read timeouts (shared by its protocol objects).

    :param max_connections: most connections open at once (keep it below the file descriptor limit)
    :param header_timeout: seconds for a request's headers to arrive, from its first byte (for a connection's
        first request: from its accept, the TLS handshake included)
    :param body_timeout: seconds for its body to arrive, after its headers
    :param tls: the server's TLS settings (``None``: plain HTTP); the handshake is done here, counted and timed
    :param max_header_bytes: most bytes in a request's head
    :param max_headers: most headers in a request
    """

    def __init__(
        self,
        max_connections: int,
        header_timeout: float = 5.0,
        body_timeout: float = 10.0,
        tls: ssl.SSLContext | None = None,
        max_header_bytes: int = MAX_HEADER_BYTES,
        max_headers: int = MAX_HEADERS,
    ) -> None:
        self.max_connections = int(max_connections)
        self.header_timeout, self.body_timeout = float(header_timeout), float(body_timeout)
        self.tls = tls
        self.max_header_bytes, self.max_headers = int(max_header_bytes), int(max_headers)
        self.open: dict[Any, None] = {}  # insertion-ordered: the oldest first
        self.refused = self.evicted = self.timed_out = self.handshake_failed = self.too_large = 0
        self._sweeper: asyncio.Task | None = None

    def admit(self, protocol: Any) -> bool:
        """Register a new connection; ``False`` if it must be closed (the cap is reached and no connection
        is half-open). Over the cap, the oldest half-open connection is closed to make room."""
        if self._sweeper is None or self._sweeper.done():
            self._sweeper = asyncio.get_running_loop().create_task(self._sweep())
        if len(self.open) >= self.max_connections:
            victim = next((p for p in self.open if not p._guard_served), None)
            if victim is None:
                self.refused += 1
                return False
            self.evicted += 1
            self.drop(victim)
            victim._guard_close()
        self.open[protocol] = None
        return True

    def adopt(self, protocol: Any) -> None:
        """Count a connection that another protocol object already counted (a WebSocket after its upgrade)."""
        self.open[protocol] = None

    def drop(self, protocol: Any) -> None:
        self.open.pop(protocol, None)

    async def _sweep(self) -> None:
        while True:
            await asyncio.sleep(0.25)
            now = time.monotonic()
            for protocol in list(self.open):
                since = protocol._guard_since
                if since is None:
                    continue
                headers = protocol._guard_headers_at
                late = (now - since > self.header_timeout) if headers is None else (now - headers > self.body_timeout)
                if late:
                    self.timed_out += 1
                    self.drop(protocol)
                    protocol._guard_close()


def _too_large(transport: Any, what: str) -> None:
    """Answer ``431`` naming the limit and close (a head over the limits is never parsed further)."""
    body = json.dumps({"error": f"headers: {what}", "field": "headers"}).encode()
    transport.write(b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n"
                    b"connection: close\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n" + body)
    transport.close()


def guarded_protocol(base: type, guard: ConnectionGuard) -> type:
    """uvicorn's HTTP protocol class ``base`` (h11's or httptools') under ``guard``'s cap, timeouts, header limits
    and TLS handshake.

    :param base: the protocol class uvicorn would use
    :param guard: the shared limits
    :return: a subclass, for ``uvicorn.Config(http=...)``
    """

    class Guarded(base):
        def connection_made(self, transport) -> None:  # type: ignore[override]
            self._guard_since: float | None = time.monotonic()  # reading a request since (None: idle)
            self._guard_headers_at: float | None = None
            self._guard_served = False  # completed a request at least once
            self._guard_cycle = None
            self._guard_raw = transport  # the TCP connection (under TLS: below the TLS transport)
            self._guard_made = False  # uvicorn's protocol has its transport (after the handshake)
            self._guard_early: list[bytes] | None = None  # bytes decrypted before that
            self._guard_head = 0  # bytes of the request head read so far
            self._guard_header_count = 0
            if not guard.admit(self):
                transport.close()
                return
            if guard.tls is None:
                self._guard_made = True
                super().connection_made(transport)
                return
            # The TLS layer goes in now, before the event loop can deliver the ClientHello (start_tls would
            # run a loop iteration later); done, it reports to _guard_handshaken.
            loop = asyncio.get_running_loop()
            self._guard_early = []
            waiter = loop.create_future()
            layer = sslproto.SSLProtocol(loop, self, guard.tls, waiter, server_side=True, call_connection_made=False,
                                         ssl_handshake_timeout=guard.header_timeout)  # fmt: skip
            transport.set_protocol(layer)
            layer.connection_made(transport)
            waiter.add_done_callback(lambda done: self._guard_handshaken(done, layer))

        def _guard_handshaken(self, done: asyncio.Future, layer) -> None:
            failed = done.cancelled() or done.exception() is not None
            if failed or self not in guard.open:  # a failed handshake, or evicted or timed out during it
                guard.handshake_failed += failed
                guard.drop(self)
                self._guard_raw.close()
                return
            self._guard_made = True
            made = getattr(layer, "_get_app_transport", None)  # Python 3.11+; 3.10 built it at once
            base.connection_made(self, made() if made is not None else layer._app_transport)
            early, self._guard_early = self._guard_early, None
            for chunk in early:
                self.data_received(chunk)

        def _guard_close(self) -> None:
            if self._guard_made:
                self.connections.discard(self)  # uvicorn's count (its limit_concurrency) drops now, not at the close
                self.transport.close()
            else:
                self._guard_raw.close()

        def connection_lost(self, exc) -> None:  # type: ignore[override]
            guard.drop(self)
            if self._guard_made:
                super().connection_lost(exc)

        def on_header(self, name: bytes, value: bytes) -> None:  # httptools' callback, once per header
            self._guard_header_count += 1
            super().on_header(name, value)

        def handle_websocket_upgrade(self, *args) -> None:
            guard.drop(self)  # the WebSocket protocol object counts the connection from now (guarded_websocket)
            super().handle_websocket_upgrade(*args)

        def data_received(self, data: bytes) -> None:
            if self._guard_early is not None:  # decrypted right after the handshake, before it was reported
                self._guard_early.append(data)
                return
            if self._guard_since is None:
                self._guard_since = time.monotonic()
            in_head = self._guard_headers_at is None
            super().data_received(data)
            if self not in guard.open:  # upgraded, or closed
                return
            cycle = getattr(self, "cycle", None)
            if cycle is not None and cycle is not self._guard_cycle:
                if self._guard_headers_at is None:
                    self._guard_headers_at = time.monotonic()
                    self._guard_head = 0
                    # a head that arrived whole in one read: its size and count checked now
                    fields = cycle.scope["headers"]
                    size = len(cycle.scope.get("raw_path", b"")) + sum(len(k) + len(v) + 4 for k, v in fields)
                    if len(fields) > guard.max_headers or size > guard.max_header_bytes:
                        self._guard_refuse(f"the request head is over {guard.max_header_bytes} bytes or "
                                           f"{guard.max_headers} headers")  # fmt: skip
                        return
                    self._guard_header_count = 0
                if not cycle.more_body:  # the whole request is in: reading is over until the next one
                    self._guard_cycle, self._guard_served = cycle, True
                    self._guard_since = self._guard_headers_at = None
            elif in_head:
                # Still in the head after this chunk: bounded here, whatever the parser keeps (httptools
                # buffers a header of any size; one chunk is at most the event loop's read size).
                self._guard_head += len(data)
                if self._guard_head > guard.max_header_bytes or self._guard_header_count > guard.max_headers:
                    self._guard_refuse(f"the request head is over {guard.max_header_bytes} bytes or "
                                       f"{guard.max_headers} headers")  # fmt: skip

        def _guard_refuse(self, what: str) -> None:
            cycle = getattr(self, "cycle", None)
            if cycle is not None:  # its request reads as a disconnect: the app, if it started, does nothing for it
                cycle.disconnected = True
                cycle.message_event.set()
            guard.too_large += 1
            guard.drop(self)
            self.connections.discard(self)
            _too_large(self.transport, what)

    Guarded.__name__ = Guarded.__qualname__ = f"Guarded{base.__name__}"
    return Guarded


def guarded_websocket(base: type, guard: ConnectionGuard) -> type:
    """uvicorn's WebSocket protocol class ``base``, its connection counted under ``guard``'s cap until it closes,
    and, with uvicorn's sans-I/O protocol on a plain connection, able to hand its connection to another process
    after the upgrade (:meth:`hold`, :meth:`detach`; the application finds the protocol object in its scope's
    extension :data:`CONNECTION`).

    :param base: the WebSocket protocol class uvicorn would use
    :param guard: the shared limits
    :return: a subclass, for ``uvicorn.Config(ws=...)``
    """

    class GuardedWebSocket(base):
        _guard_served = True  # it completed a request (its upgrade): not evicted as half-open
        _guard_since = None
        on_lost: Any = None  # called once the connection is closed (a handed one: told nothing else by uvicorn)

        def connection_made(self, transport) -> None:  # type: ignore[override]
            guard.adopt(self)
            super().connection_made(transport)
            self._guard_app, self.app = self.app, self._guard_scoped

        async def _guard_scoped(self, scope, receive, send) -> None:
            scope.setdefault("extensions", {})[CONNECTION] = self
            await self._guard_app(scope, receive, send)

        def hold(self) -> bool:
            """Stop reading before the upgrade is answered (so that every byte after the answer stays in the
            socket, for :meth:`detach`); ``False`` if this connection cannot be handed over (TLS, or another
            protocol class than uvicorn's sans-I/O one)."""
            if guard.tls is not None or not hasattr(self, "stop_keepalive") or not hasattr(self, "conn"):
                return False
            self.transport.pause_reading()
            return True

        def detach(self) -> int | None:
            """After the upgrade's answer: a duplicate of the connection's descriptor, which the caller hands on
            (the protocol reads nothing more, sends no more pings, and keeps its own descriptor until closed);
            ``None``, reading resumed, if the client sent bytes before the answer."""
            reader = getattr(self.conn, "reader", None)
            if not self.queue.empty() or len(getattr(reader, "buffer", b"")) or self.transport.is_closing():
                self.transport.resume_reading()
                return None
            self.stop_keepalive()
            return os.dup(self.transport.get_extra_info("socket").fileno())

        def connection_lost(self, exc) -> None:  # type: ignore[override]
            guard.drop(self)
            super().connection_lost(exc)
            if self.on_lost is not None:
                self.on_lost()

        def _guard_close(self) -> None:
            self.transport.close()

    GuardedWebSocket.__name__ = GuardedWebSocket.__qualname__ = f"Guarded{base.__name__}"
    return GuardedWebSocket


def websocket_protocol() -> type | None:
    """The WebSocket protocol class uvicorn picks (``websockets``, else ``wsproto``; ``None``: neither installed)."""
    from uvicorn.protocols.websockets.auto import AutoWebSocketsProtocol

    return AutoWebSocketsProtocol  # type: ignore[return-value]


def uvicorn_protocol(kind: str = "auto") -> type:
    """The HTTP protocol class uvicorn picks for ``http=kind`` (httptools when installed, else h11).

    :raises ValueError: ``kind`` is not ``auto``, ``httptools`` or ``h11``
    """
    if kind not in HTTP_PARSERS:
        raise ValueError(f"http must be one of {', '.join(map(repr, HTTP_PARSERS))}, got {kind!r}")
    if kind in ("auto", "httptools"):
        try:
            from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

            return HttpToolsProtocol
        except ImportError:
            if kind == "httptools":
                raise
    from uvicorn.protocols.http.h11_impl import H11Protocol

    return H11Protocol


class RateLimitFilter(logging.Filter):
    """A token bucket over log records: a burst of ``burst``, then ``rate`` per second; the records dropped are
    counted and announced by the next one let through. Records of the ``asyncio`` logger lose their traceback
    (one per failed ``accept`` under a flood of connections).

    :param burst: records let through at once
    :param rate: records per second after the burst
    """

    def __init__(self, burst: int = 20, rate: float = 0.2) -> None:
        super().__init__()
        self.burst, self.rate = float(burst), float(rate)
        self.tokens, self.stamp, self.dropped = float(burst), time.monotonic(), 0

    def filter(self, record: logging.LogRecord) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens < 1.0:
            self.dropped += 1
            return False
        self.tokens -= 1.0
        if record.name == "asyncio":
            record.exc_info, record.exc_text = None, None
        if self.dropped:
            record.msg = f"{record.getMessage()} ({self.dropped} earlier log messages suppressed)"
            record.args, self.dropped = None, 0
        return True


LOGGERS = ("asyncio", "uvicorn", "uvicorn.error", "uvicorn.access", "envs.serve")


def limit_logging(burst: int = 20, rate: float = 0.2) -> RateLimitFilter:
    """Put one :class:`RateLimitFilter` on the server's loggers (:data:`LOGGERS`).

    :return: the filter (its ``dropped`` counts what it holds back now)
    """
    limiter = RateLimitFilter(burst, rate)
    for name in LOGGERS:
        logger = logging.getLogger(name)
        for old in [f for f in logger.filters if isinstance(f, RateLimitFilter)]:
            logger.removeFilter(old)
        logger.addFilter(limiter)
    return limiter
