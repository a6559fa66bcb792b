"""Who may talk to the planner server: tokens, the ``Host`` allowlist, and the default token file.

Standard library only: the server (:mod:`envs.serve.app`, :mod:`envs.commands.serve`) and the client
(:mod:`envs.serve.client`, which finds the default token file of a server on its own machine) share it.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import secrets
import stat
import tempfile
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

    :param path: the token file (replaced)
    :return: the token
    :raises ValueError: the folder belongs to another user or others may write to it
    """
    folder = path.parent
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = folder.stat()
    if (hasattr(os, "getuid") and info.st_uid != os.getuid()) or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise ValueError(f"token folder {str(folder)!r} belongs to another user or others may write to it")
    os.chmod(folder, 0o700)
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
            return f"peer-{peer}"
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
