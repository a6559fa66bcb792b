"""Signatures of the files a run writes itself, so that ``--resume`` unpickles nothing else.

A training checkpoint is an SB3 ``model.zip`` and a pickled replay buffer: loading them runs the
pickles inside. ``sb3-graph train`` therefore signs every checkpoint file when it writes it (an
HMAC-SHA256 of the content, keyed with a secret of this user on this machine) and, on
``--resume``, loads only files whose signature checks out. A run folder copied from somewhere
else, or a checkpoint replaced after it was written, is refused: its signatures were made with
another key or are missing. The run's ``config.yml`` and ``run.json`` are signed the same way
(:func:`write_signed`), since they decide what a resumed run builds and records. A plain digest
stored next to the files would not do this, since whoever hands over the folder can write matching digests too.

The key is 32 random bytes in ``$SB3_GRAPH_KEY_FILE``, else
``$XDG_CONFIG_HOME/sb3-graph/file-key`` (``~/.config/sb3-graph/file-key``), created with mode
0600 on first use. Copying it to another machine of yours lets that machine resume your runs.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat
import tempfile
from pathlib import Path

from sb3_graph.files.safe_values import UnsafeValueError, load_json, read_text_file

KEY_ENV = "SB3_GRAPH_KEY_FILE"
SIGNATURES = "signatures.json"
KEY_BYTES = 32
# Largest signatures.json read (one line per file of a run folder).
MAX_MANIFEST_BYTES = 1 << 20


class SignatureError(ValueError):
    """A file without a valid signature of this machine's key."""


def key_path() -> Path:
    """Where the signing key lives (see the module docstring)."""
    if os.environ.get(KEY_ENV):
        return Path(os.environ[KEY_ENV])
    config = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")
    return config / "sb3-graph" / "file-key"


def _key() -> bytes:
    path = key_path()
    if path.is_file():
        key = path.read_bytes()
        if len(key) >= KEY_BYTES:
            return key
    path.parent.mkdir(parents=True, exist_ok=True)
    key = secrets.token_bytes(KEY_BYTES)
    # O_EXCL: two processes that create the key at once do not overwrite each other's
    try:
        handle = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return path.read_bytes()
    with os.fdopen(handle, "wb") as file:
        file.write(key)
    return key


def file_signature(path: str | Path, key: bytes | None = None) -> str:
    """HMAC-SHA256 (hex) of a file's content under the signing key.

    :raises SignatureError: not a regular file (a FIFO or device would be read forever)
    """
    digest = hmac.new(key if key is not None else _key(), digestmod=hashlib.sha256)
    try:
        mode = os.stat(path).st_mode
    except OSError as error:
        raise SignatureError(f"{path}: cannot read it ({error.strerror or error})") from None
    if not stat.S_ISREG(mode):
        raise SignatureError(f"{path} is not a regular file (a FIFO, device or folder is never loaded)")
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _manifest(folder: Path) -> dict[str, str]:
    path = folder / SIGNATURES
    if not path.exists():
        return {}
    try:
        data = load_json(read_text_file(path, SIGNATURES, MAX_MANIFEST_BYTES), SIGNATURES)
    except UnsafeValueError:  # a device, a FIFO, a huge or broken file: nothing counts as signed
        return {}
    if not isinstance(data, dict):
        return {}
    return {k: v for k, v in data.items() if isinstance(k, str) and isinstance(v, str)}


def sign(path: str | Path) -> None:
    """Record the signature of ``path`` in its folder's ``signatures.json``."""
    path = Path(path)
    manifest = _manifest(path.parent)
    manifest[path.name] = file_signature(path)
    manifest = {name: value for name, value in manifest.items() if (path.parent / name).is_file()}
    temporary = path.parent / f".{SIGNATURES}.tmp"
    temporary.write_text(json.dumps(manifest, indent=1, sort_keys=True))
    os.replace(temporary, path.parent / SIGNATURES)


def write_signed(path: str | Path, text: str) -> Path:
    """Write a text file of the run (``config.yml``, ``run.json``) and sign it.

    The text goes to a temporary file that then replaces ``path``: a symbolic link or a file that
    someone put at ``path`` is replaced, never written through.

    :param path: the file
    :param text: its content
    :return: ``path``
    """
    path = Path(path)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w") as file:
            file.write(text)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    sign(path)
    return path


def verify(path: str | Path) -> None:
    """Check that ``path`` is exactly a file this machine's key signed.

    :raises SignatureError: no signature, or one that does not match
    """
    path = Path(path)
    expected = _manifest(path.parent).get(path.name)
    if expected is None:
        raise SignatureError(f"{path} has no signature in {path.parent / SIGNATURES}")
    if not hmac.compare_digest(expected, file_signature(path)):
        raise SignatureError(f"{path} does not match its signature (changed since written, or signed elsewhere)")


TRUST_HINT = "--trust-run-files loads it: only for your own run, e.g. one copied from another machine of yours"


def verify_run_file(path: str | Path, trust: bool = False) -> None:
    """Check a file of a run folder before ``--resume`` reads it (unless ``trust``).

    :param path: ``config.yml``, ``run.json`` or a checkpoint
    :param trust: skip the check (``--trust-run-files``)
    :raises SignatureError: unsigned or changed, with the hint to :data:`TRUST_HINT`
    """
    if trust:
        return
    try:
        verify(path)
    except SignatureError as error:
        raise SignatureError(f"{error}; it is not read ({TRUST_HINT})") from None
