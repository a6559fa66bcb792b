"""A plain WebSocket handed from the server's event loop to the planning process of its stream.

With ``--workers N`` a fast-path step would cross two processes each way: uvicorn's WebSocket protocol on the
event loop, then the socket pair to the stream's worker (:mod:`envs.serve.workers`). Once the upgrade has passed
the ``Host``, token and owner checks, the server instead passes a duplicate of the connection's descriptor to
that worker (``SCM_RIGHTS``), which reads the step frames, plans and writes the answers itself; the event loop
keeps its own descriptor (the connection stays counted under the connection cap) but reads nothing more from it.
A TLS connection is never handed (its keys live in the event loop's process).

:class:`HandedSocket` is the worker's end: the server side of RFC 6455 for one connection, non-blocking (a
client that stops reading cannot stall its worker: answers wait in a buffer and the connection is not read
until they are sent), with client frames required to be masked, control frames answered (ping: pong; close:
close), fragmented messages joined, and messages over ``max_size`` closed with 1009.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Callable

from envs.serve.websocket import apply_mask, frame_head

# close codes (RFC 6455 7.4.1)
NORMAL, PROTOCOL_ERROR, TOO_BIG = 1000, 1002, 1009
_READ = 1 << 16


def server_frame(payload: bytes, opcode: int = 0x2) -> bytes:
    """One unmasked, final frame as a server sends it (binary by default)."""
    return frame_head(opcode, len(payload)) + payload


def close_frame(code: int) -> bytes:
    return server_frame(struct.pack("!H", code), opcode=0x8)


class HandedSocket:
    """The worker's end of a handed WebSocket (the server side of the protocol, non-blocking).

    :param sock: the connection (a duplicate of the server's descriptor), after the upgrade
    :param key: the server's number for this connection
    :param sid: the stream whose steps it carries
    :param max_size: largest message accepted [bytes]
    """

    def __init__(self, sock: socket.socket, key: int, sid: str, max_size: int) -> None:
        sock.setblocking(False)
        self.sock, self.key, self.sid, self.max_size = sock, int(key), sid, int(max_size)
        self.inbox = bytearray()
        self.outbox = bytearray()
        self.message: bytearray | None = None  # a fragmented message being joined
        self.text = False  # its first frame was text
        self.closed = False  # no more messages are read (a close was sent or received, or the peer went)
        self.last_used = time.monotonic()

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self) -> bool:
        """Read what the socket holds; ``False`` once the peer is gone."""
        try:
            data = self.sock.recv(_READ)
        except BlockingIOError:
            return True
        except OSError:
            return False
        if not data:
            return False
        self.inbox += data
        return True

    def messages(self, answer: Callable[[bytes, bool], bytes]) -> None:
        """Answer every whole message in the inbox with ``answer(message, is_text)`` (its reply is sent as one
        binary frame), control frames as the protocol says; stops while answers wait to be sent, so that a
        client that does not read them holds only its own replies."""
        while not self.closed and not self.outbox:
            frame = self._next_frame()
            if frame is None:
                return
            fin, opcode, payload = frame
            if opcode == 0x8:  # close: echo its code, and the connection ends
                self.send(close_frame(struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else NORMAL))
                self.closed = True
                return
            if opcode == 0x9:
                self.send(server_frame(payload, opcode=0xA))
                continue
            if opcode == 0xA:
                continue
            if opcode in (0x1, 0x2):
                if self.message is not None:
                    return self.fail(PROTOCOL_ERROR)
                self.message, self.text = bytearray(payload), opcode == 0x1
            elif opcode == 0x0 and self.message is not None:
                self.message += payload
            else:
                return self.fail(PROTOCOL_ERROR)
            if len(self.message) > self.max_size:
                return self.fail(TOO_BIG)
            if fin:
                message, self.message = bytes(self.message), None
                self.last_used = time.monotonic()
                self.send(server_frame(answer(message, self.text)))

    def _next_frame(self) -> tuple[bool, int, bytes] | None:
        """The next whole frame of the inbox (removed from it), unmasked; ``None`` if it has not all arrived (or
        the frame broke the protocol: the connection is then failed)."""
        inbox = self.inbox
        if len(inbox) < 2:
            return None
        b0, b1 = inbox[0], inbox[1]
        opcode, n, at = b0 & 0x0F, b1 & 0x7F, 2
        if b0 & 0x70 or not b1 & 0x80 or (opcode >= 0x8 and (n > 125 or not b0 & 0x80)) or opcode in (3, 4, 5, 6, 7):
            self.fail(PROTOCOL_ERROR)  # reserved bits (no extension was agreed), an unmasked or bad control frame
            return None
        if n == 126:
            if len(inbox) < 4:
                return None
            n, at = struct.unpack_from("!H", inbox, 2)[0], 4
        elif n == 127:
            if len(inbox) < 10:
                return None
            n, at = struct.unpack_from("!Q", inbox, 2)[0], 10
        if n > self.max_size:
            self.fail(TOO_BIG)
            return None
        end = at + 4 + n
        if len(inbox) < end:
            return None
        mask = bytes(inbox[at : at + 4])
        payload = apply_mask(memoryview(inbox)[at + 4 : end], mask) if n else b""
        del inbox[:end]
        return bool(b0 & 0x80), opcode, payload

    def send(self, data: bytes) -> None:
        """Send ``data``, keeping what the socket does not take now (see :meth:`flush`)."""
        if self.outbox:
            self.outbox += data
            return
        try:
            sent = self.sock.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:
            self.closed = True
            return
        if sent < len(data):
            self.outbox += data[sent:]

    def flush(self) -> None:
        """Send what waits (the socket was writable)."""
        try:
            sent = self.sock.send(self.outbox)
        except BlockingIOError:
            return
        except OSError:
            self.outbox.clear()
            self.closed = True
            return
        del self.outbox[:sent]

    def fail(self, code: int) -> None:
        """Close with ``code`` (the peer broke the protocol or sent too much)."""
        self.inbox.clear()
        self.send(close_frame(code))
        self.closed = True

    def close(self) -> None:
        """Let go of the descriptor (the server closes its own)."""
        self.closed = True
        try:
            self.sock.close()
        except OSError:
            pass
