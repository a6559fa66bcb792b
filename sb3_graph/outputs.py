"""Output folders that are whole or absent: a failed command never leaves a half-written ``--out``.

:func:`staged_folder` hands out a hidden temporary folder next to the destination; the command
writes everything there, and only when it succeeds is the folder renamed to the destination (one
``rename`` on the same file system). On any failure, Ctrl-C included, the temporary folder and
any parent folders made for it are removed, so the same command can simply be run again.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputError(ValueError):
    """A destination that cannot be written (the message names it and the reason)."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _make_parents(folder: Path, flag: str) -> list[Path]:
    """Create the missing parents of ``folder``; return the ones created (deepest last)."""
    missing = []
    parent = folder.parent
    while not parent.exists() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(f"{flag}: cannot create {str(folder)!r}: {error.strerror or error}") from None
    return list(reversed(missing))


def check_destination(out: Path, flag: str = "--out") -> None:
    """Refuse a destination that exists (a file or a folder) before any work starts.

    :raises OutputError: naming the flag and the path
    """
    if out.exists() or out.is_symlink():
        kind = "a folder" if out.is_dir() else "a file"
        raise OutputError(f"{flag}: {str(out)!r} exists ({kind}); choose a new folder (reports are never overwritten)")


@contextmanager
def staged_folder(out: str | Path, flag: str = "--out") -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` when the block succeeds.

    :param out: the destination; it must not exist
    :param flag: the option named in messages
    :raises OutputError: ``out`` exists, or its parent cannot be created or written
    """
    out = Path(out)
    check_destination(out, flag)
    created = _make_parents(out, flag)
    try:
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    except OSError as error:
        _remove_empty(created)
        raise OutputError(f"{flag}: cannot write into {str(out.parent)!r}: {error.strerror or error}") from None
    try:
        os.chmod(staging, 0o777 & ~_umask())  # mkdtemp makes it private; a report folder is not
        yield staging
        try:
            os.rename(staging, out)
        except OSError as error:
            raise OutputError(f"{flag}: cannot create {str(out)!r}: {error.strerror or error}") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        _remove_empty(created)
        raise


def _remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):
        try:
            folder.rmdir()
        except OSError:
            return


def write_file_atomically(path: str | Path, write, flag: str = "OUT") -> Path:
    """Write a file through ``write(temporary_path)`` and rename it to ``path`` when that succeeds.

    :param path: the destination file (must not exist)
    :param write: a function that writes the file at the path it is given
    :param flag: the argument named in messages
    :return: ``path``
    :raises OutputError: ``path`` exists or its folder cannot be written
    """
    path = Path(path)
    if path.exists() or path.is_symlink():
        raise OutputError(f"{flag}: {str(path)!r} exists; choose a new file name")
    created = _make_parents(path, flag)
    try:
        handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.partial-", dir=path.parent)
    except OSError as error:
        _remove_empty(created)
        raise OutputError(f"{flag}: cannot write into {str(path.parent)!r}: {error.strerror or error}") from None
    os.close(handle)
    try:
        write(Path(temporary))
        os.chmod(temporary, 0o666 & ~_umask())
        os.rename(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        _remove_empty(created)
        raise
    return path
