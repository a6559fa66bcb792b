"""A minimal blocking WebSocket client (RFC 6455): what the planner client needs for the fast path, in the
standard library and numpy (binary messages, ping answered, no extensions).

:func:`frame_head` and :func:`apply_mask` also serve the server's end of a handed connection
(:mod:`envs.serve.handoff`).

One request and one answer at a time on one connection: :meth:`WebSocket.send` writes a masked binary frame,
:meth:`WebSocket.recv` reads the next data message. Any failure (a timeout mid-frame, a close, a reset) leaves
the connection unusable: the caller drops it and opens another.
"""

from __future__ import annotations

import base64
import hashlib
import os
import socket
import ssl
import struct

import numpy as np

_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_MAX_HEAD = 16 * 1024


class UpgradeRefused(ConnectionError):
    """The server answered the upgrade with an HTTP status other than 101.

    :param status: that status
    """

    def __init__(self, status: int) -> None:
        super().__init__(f"WebSocket upgrade refused ({status})")
        self.status = status


class WebSocket:
    """A client connection (use :meth:`connect`).

    :param sock: the connected socket, after the upgrade
    :param max_size: largest message accepted [bytes]
    """

    def __init__(self, sock: socket.socket, max_size: int = 1 << 24) -> None:
        self.sock, self.max_size = sock, int(max_size)
        self._buffer = bytearray()

    @classmethod
    def connect(cls, host: str, port: int, path: str, headers: dict[str, str], timeout: float,
                ssl_context: ssl.SSLContext | None = None) -> WebSocket:  # fmt: skip
        """Open a connection and upgrade it.

        :param headers: extra request headers (``Authorization``)
        :param timeout: seconds for the connection and the upgrade
        :param ssl_context: TLS (``wss://``)
        :raises UpgradeRefused: the server answered another status
        :raises OSError: no connection
        """
        sock = socket.create_connection((host, port), timeout=timeout)
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if ssl_context is not None:
                sock = ssl_context.wrap_socket(sock, server_hostname=host)
            key = base64.b64encode(os.urandom(16))
            name = f"[{host}]" if ":" in host else host
            lines = [f"GET {path} HTTP/1.1", f"Host: {name}:{port}", "Upgrade: websocket", "Connection: Upgrade",
                     f"Sec-WebSocket-Key: {key.decode()}", "Sec-WebSocket-Version: 13",
                     *(f"{k}: {v}" for k, v in headers.items())]  # fmt: skip
            sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"))
            head = b""
            while b"\r\n\r\n" not in head:
                chunk = sock.recv(4096)
                if not chunk or len(head) > _MAX_HEAD:
                    raise ConnectionError("the server closed the connection during the WebSocket upgrade")
                head += chunk
            head, rest = head.split(b"\r\n\r\n", 1)
            status_line, *fields = head.decode("latin-1").split("\r\n")
            parts = status_line.split(" ", 2)
            status = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0
            if status != 101:
                raise UpgradeRefused(status)
            accept = {k.strip().lower(): v.strip() for k, v in (f.split(":", 1) for f in fields if ":" in f)}
            expected = base64.b64encode(hashlib.sha1(key + _GUID).digest()).decode()
            if accept.get("sec-websocket-accept") != expected:
                raise ConnectionError("the server's WebSocket upgrade answer does not match the key")
        except BaseException:
            sock.close()
            raise
        ws = cls(sock)
        ws._buffer += rest
        return ws

    def send(self, data: bytes, timeout: float | None = None, opcode: int = 0x2) -> None:
        """Send one message (binary by default), masked as a client must."""
        n = len(data)
        head = frame_head(opcode, n, masked=True)
        mask = os.urandom(4)
        if n:
            data = apply_mask(data, mask)
        self.sock.settimeout(timeout)
        self.sock.sendall(head + mask + data)

    def recv(self, timeout: float | None = None) -> bytes:
        """The next data message (pings answered, pongs skipped).

        :raises ConnectionError: the server closed the connection
        :raises TimeoutError: no whole message within ``timeout`` (the connection is then unusable)
        """
        self.sock.settimeout(timeout)
        message, first = bytearray(), None
        while True:
            b0, b1 = self._read(2)
            opcode, n = b0 & 0x0F, b1 & 0x7F
            if n == 126:
                n = struct.unpack("!H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack("!Q", self._read(8))[0]
            if n > self.max_size or len(message) + n > self.max_size:
                raise ConnectionError(f"a WebSocket message over {self.max_size} bytes")
            mask = self._read(4) if b1 & 0x80 else None
            payload = self._read(n)
            if mask is not None and n:
                payload = apply_mask(payload, mask)
            if opcode == 0x8:
                raise ConnectionError("the server closed the WebSocket")
            if opcode == 0x9:
                self.send(bytes(payload), timeout, opcode=0xA)
                continue
            if opcode == 0xA:
                continue
            if opcode in (0x1, 0x2):
                first = opcode
            elif opcode != 0x0 or first is None:
                raise ConnectionError(f"unexpected WebSocket frame (opcode {opcode})")
            message += payload
            if b0 & 0x80:
                return bytes(message)

    def _read(self, n: int) -> bytes:
        buffer = self._buffer
        while len(buffer) < n:
            chunk = self.sock.recv(max(65536, n - len(buffer)))
            if not chunk:
                raise ConnectionError("the server closed the connection")
            buffer += chunk
        data = bytes(buffer[:n])
        del buffer[:n]
        return data

    def close(self) -> None:
        """Close without waiting for the server's answer."""
        try:
            self.send(struct.pack("!H", 1000), 0.05, opcode=0x8)
        except OSError:
            pass
        try:
            self.sock.close()
        except OSError:
            pass


def frame_head(opcode: int, n: int, masked: bool = False) -> bytes:
    """The head of a final frame with a payload of ``n`` bytes (``masked``: as a client sends it, the mask to
    follow)."""
    bit = 0x80 if masked else 0
    if n < 126:
        return struct.pack("!BB", 0x80 | opcode, bit | n)
    if n < 1 << 16:
        return struct.pack("!BBH", 0x80 | opcode, bit | 126, n)
    return struct.pack("!BBQ", 0x80 | opcode, bit | 127, n)


def apply_mask(data: bytes | bytearray | memoryview, mask: bytes) -> bytes:
    """``data`` XOR the 4-byte ``mask`` repeated (RFC 6455's masking, both ways)."""
    n = len(data)
    return (np.frombuffer(data, np.uint8) ^ np.frombuffer(mask * ((n + 3) // 4), np.uint8, n)).tobytes()
