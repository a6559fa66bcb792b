"""Connection limits of the planner server, and logging that an attack cannot turn into a full disk.

uvicorn closes an idle kept-alive connection after ``timeout_keep_alive`` and answers 503 above
``limit_concurrency``, but it has no limit on connections at accept, and no timeout for a request whose
headers or body never finish arriving (it arms its keep-alive timer only after a response): about a
thousand half-sent requests then hold every file descriptor. :func:`guarded_protocol` wraps uvicorn's
HTTP protocol class so that

- at most ``max_connections`` connections are open: a new one over the cap closes the oldest connection
  that has never completed a request (a half-open one), or itself when every open connection has;
- a request's headers must arrive within ``header_timeout`` seconds of its first byte (of the
  connection's opening, for its first request), and its body within ``body_timeout`` seconds more:
  a sweep every quarter second closes the connections that are late.

:class:`RateLimitFilter` keeps the server's log to a bounded rate, and drops the tracebacks that
the event loop attaches to a failed ``accept``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

# The listening socket's backlog. asyncio accepts up to ``backlog`` connections in one go, and an evicted
# connection's descriptor closes only a few loop iterations later, so a flood can hold about three bursts
# over the cap: 3 x 16 stays inside the 64 descriptors the server keeps in reserve (``RESERVED_FDS``).
ACCEPT_BURST = 16
# uvicorn's HTTP parsers that the server may be told to use (``serve --http``); ``auto``: httptools when installed
HTTP_PARSERS = ("auto", "httptools", "h11")


class ConnectionGuard:
    """The open connections of one server, their caps and read timeouts (shared by its protocol objects).

    :param max_connections: most connections open at once (keep it below the file descriptor limit)
    :param header_timeout: seconds for a request's headers to arrive, from its first byte
    :param body_timeout: seconds for its body to arrive, after its headers
    """

    def __init__(self, max_connections: int, header_timeout: float = 5.0, body_timeout: float = 10.0) -> None:
        self.max_connections = int(max_connections)
        self.header_timeout, self.body_timeout = float(header_timeout), float(body_timeout)
        self.open: dict[Any, None] = {}  # insertion-ordered: the oldest first
        self.refused = self.evicted = self.timed_out = 0
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
            victim.connections.discard(victim)  # uvicorn's count (its limit_concurrency) drops now, not at the close
            victim.transport.close()
        self.open[protocol] = None
        return True

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
                    protocol.transport.close()


def guarded_protocol(base: type, guard: ConnectionGuard) -> type:
    """uvicorn's HTTP protocol class ``base`` (h11's or httptools') under ``guard``'s cap and timeouts.

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
            super().connection_made(transport)
            if not guard.admit(self):
                self.connections.discard(self)
                transport.close()

        def connection_lost(self, exc) -> None:  # type: ignore[override]
            guard.drop(self)
            super().connection_lost(exc)

        def data_received(self, data: bytes) -> None:
            if self._guard_since is None:
                self._guard_since = time.monotonic()
            super().data_received(data)
            cycle = getattr(self, "cycle", None)
            if cycle is not None and cycle is not self._guard_cycle:
                if self._guard_headers_at is None:
                    self._guard_headers_at = time.monotonic()
                if not cycle.more_body:  # the whole request is in: reading is over until the next one
                    self._guard_cycle, self._guard_served = cycle, True
                    self._guard_since = self._guard_headers_at = None

    Guarded.__name__ = Guarded.__qualname__ = f"Guarded{base.__name__}"
    return Guarded


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
