"""Who may talk to the planner server: tokens, the ``Host`` allowlist, and the default token file.

Standard library only: the server (:mod:`envs.serve.app`, :mod:`envs.commands.serve`) and the client
(:mod:`envs.serve.client`, which finds the default token file of a server on its own machine) share it.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
import secrets
import stat
import tempfile
import time
from collections import OrderedDict
from collections.abc import Iterable
from pathlib import Path

# Host names that reach a loopback server (its Host header may carry any of them, with or without a port).
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is the loopback interface."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def read_tokens(path: str | Path) -> list[str]:
    """The tokens of a token file: one per line, blank lines and ``#`` comments skipped.

    :param path: the file
    :return: the tokens, in file order
    :raises ValueError: an unreadable file, or one without a token
    """
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"token file {str(path)!r} cannot be read ({error})") from None
    tokens = [line.strip() for line in lines if line.strip() and not line.strip().startswith("#")]
    if not tokens:
        raise ValueError(f"token file {str(path)!r} holds no token")
    short = next((k for k, token in enumerate(tokens) if len(token) < 16 or any(c.isspace() for c in token)), None)
    if short is not None:
        raise ValueError(f"token file {str(path)!r}: token {short + 1} is shorter than 16 characters or has a space")
    return tokens


def default_token_path(host: str, port: int) -> Path:
    """Where a server started without ``--token-file`` writes its token (and where the client looks for it):
    ``$XDG_RUNTIME_DIR/sb3-graph/serve-HOST-PORT.token``, else the same under the system's temporary folder
    with the user's id in the folder name. The folder is made private to the user (``0700``).

    :param host: the address the server binds
    :param port: its port
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    base = Path(runtime) / "sb3-graph" if runtime else Path(tempfile.gettempdir()) / f"sb3-graph-{user}"
    safe = "".join(c if c.isalnum() or c in ".-" else "_" for c in host.strip("[]"))
    return base / f"serve-{safe}-{int(port)}.token"


def write_private_token(path: Path) -> str:
    """Generate a token and write it to ``path``, readable and writable by the user only (``0600``), in a folder
    that only the user may enter (``0700``).

    A symbolic link in the folder's place is refused, never followed: another user who can write the parent
    folder (the system's temporary folder) could otherwise point it at a folder of theirs, or have the
    server change the mode of a folder it names. The folder is opened without following links and its
    mode set through that descriptor.

    :param path: the token file (replaced)
    :return: the token
    :raises ValueError: the folder is a symbolic link, not a folder, belongs to another user or others may
        write to it
    """
    folder = path.parent
    folder.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    try:
        folder.mkdir(mode=0o700)
    except FileExistsError:
        pass
    if folder.is_symlink():
        raise ValueError(f"token folder {str(folder)!r} is a symbolic link; remove it (the server makes the folder)")
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_NOFOLLOW", 0)
    try:
        handle = os.open(folder, flags)
    except OSError as error:
        raise ValueError(f"token folder {str(folder)!r} cannot be opened as a folder ({error.strerror})") from None
    try:
        info = os.fstat(handle)
        if not stat.S_ISDIR(info.st_mode):
            raise ValueError(f"token folder {str(folder)!r} is not a folder")
        if (hasattr(os, "getuid") and info.st_uid != os.getuid()) or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
            raise ValueError(f"token folder {str(folder)!r} belongs to another user or others may write to it")
        if hasattr(os, "fchmod"):
            os.fchmod(handle, 0o700)
    finally:
        os.close(handle)
    token = secrets.token_urlsafe(32)
    temporary = folder / f".{path.name}.{secrets.token_hex(4)}"
    descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
        handle.write(token + "\n")
    os.replace(temporary, path)
    return token


class Access:
    """The server's access rules: bearer tokens (one per client) and the ``Host`` names it answers to.

    :param tokens: accepted tokens (empty: no token needed; the client is then its peer address)
    :param hosts: accepted ``Host`` names, without port (``*`` accepts any)
    """

    def __init__(self, tokens: Iterable[str], hosts: Iterable[str]) -> None:
        self.tokens = [token.encode() for token in tokens]
        self.hosts = frozenset(host.lower().strip("[]") for host in hosts)

    def client(self, authorization: bytes | None, peer: str) -> str | None:
        """The client a request comes from: ``token-<k>`` for the ``k``-th token, ``peer`` without tokens.

        :param authorization: the ``Authorization`` header
        :param peer: the peer's address
        :return: the client's key, ``None`` for a missing or wrong token
        """
        if not self.tokens:
            # every loopback address (127.0.0.0/8, ::1) is this machine: one client, one quota
            return "peer-loopback" if is_loopback(peer) else f"peer-{peer}"
        if authorization is None or not authorization.startswith(b"Bearer "):
            return None
        sent = authorization[7:]
        found = None
        for k, token in enumerate(self.tokens):  # every token compared (constant time per token)
            if hmac.compare_digest(sent, token) and found is None:
                found = k
        return None if found is None else f"token-{found}"

    def host_allowed(self, header: bytes | None) -> bool:
        """Whether the ``Host`` header names this server (a DNS-rebinding page sends its own name)."""
        if "*" in self.hosts:
            return True
        if not header:
            return False
        text = header.decode("latin-1").strip().lower()
        if text.startswith("["):  # [::1]:8765
            name = text[1 : text.find("]")] if "]" in text else text
        else:
            name = text.rsplit(":", 1)[0] if text.count(":") == 1 else text
        return name in self.hosts


logger = logging.getLogger("envs.serve.access")


class FailureLimit:
    """Failed authentications per source address: a token bucket each (a burst of ``burst``, then ``rate`` per
    second), for at most ``sources`` addresses (the least recently failing forgotten first).

    A source over its budget gets ``429`` for its failing requests, without the token being compared, and is
    logged once each time it goes over; the first failure of each source is logged too (both through the
    server's rate-limited log). A valid token is never refused here: an attacker who shares an address with good
    clients (every program on this machine shares 127.0.0.1) cannot lock them out.

    :param burst: failures a source may make at once
    :param rate: failures per second after the burst
    :param sources: most sources remembered
    """

    def __init__(self, burst: int = 20, rate: float = 2.0, sources: int = 4096) -> None:
        self.burst, self.rate, self.sources = float(burst), float(rate), int(sources)
        self._buckets: OrderedDict[str, list[float]] = OrderedDict()  # source -> [tokens, stamp, over]
        self.failed = self.limited = 0

    def over(self, source: str) -> bool:
        """Whether ``source`` is over its budget now (its next failing request gets 429)."""
        bucket = self._buckets.get(source)
        if bucket is None:
            return False
        now = time.monotonic()
        return min(self.burst, bucket[0] + (now - bucket[1]) * self.rate) < 1.0

    def failure(self, source: str) -> bool:
        """Count a failed authentication of ``source``; ``False`` once it is over its budget (answer 429)."""
        now = time.monotonic()
        self.failed += 1
        bucket = self._buckets.get(source)
        if bucket is None:
            if len(self._buckets) >= self.sources:
                self._buckets.popitem(last=False)
            bucket = self._buckets[source] = [self.burst, now, 0.0]
            logger.warning("failed authentication from %s (a missing or wrong token)", source)
        else:
            self._buckets.move_to_end(source)
        bucket[0] = min(self.burst, bucket[0] + (now - bucket[1]) * self.rate)
        bucket[1] = now
        if bucket[0] < 1.0:
            self.limited += 1
            if not bucket[2]:
                bucket[2] = 1.0
                logger.warning("%s: more than %d failed authentications at once; its failing requests get 429 "
                               "until it slows below %g per second", source, int(self.burst), self.rate)
            return False
        bucket[0] -= 1.0
        if bucket[0] >= self.burst - 1.0:
            bucket[2] = 0.0  # recovered: a later flood is logged again
        return True
