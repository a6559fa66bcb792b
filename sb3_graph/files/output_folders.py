"""Output folders that are whole or absent: a failed command never leaves a half-written ``--out``.

:func:`staged_folder` hands out a hidden temporary folder next to the destination; the command
writes everything there, and only when it succeeds is the folder renamed to the destination (one
``rename`` on the same file system). On any failure, Ctrl-C included, the temporary folder and
any parent folders made for it are removed, so the same command can simply be run again. SIGTERM
counts as Ctrl-C there. With ``overwrite``, an existing folder is replaced as a whole only once the
new one is complete: never a mix of two runs' files.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


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
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM (a scheduler, ``kill``, a closed terminal's job) raises
    ``KeyboardInterrupt`` as Ctrl-C does, so that the same clean-up runs. A handler that the
    program set itself is kept; outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) not in (
        signal.SIG_DFL,
        None,
    ):
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _check_replaceable(out: Path, flag: str) -> None:
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise OutputError(f"{flag}: {str(out)!r} is a file or a link; --overwrite replaces a folder only")


def _publish(staging: Path, out: Path, flag: str) -> None:
    """Rename ``staging`` to ``out``; an existing ``out`` is moved aside first and removed only
    once the new folder is in place (on failure it is put back): the old whole or the new whole."""
    if not out.exists():
        os.rename(staging, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    os.rmdir(old)
    os.rename(out, old)
    try:
        os.rename(staging, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def staged_folder(out: str | Path, flag: str = "--out", overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` when the block succeeds.

    SIGTERM cleans up as Ctrl-C does (:func:`sigterm_as_interrupt`).

    :param out: the destination; it must not exist, unless ``overwrite``
    :param flag: the option named in messages
    :param overwrite: replace an existing folder ``out`` as a whole, once the new one is complete
        (a failed command leaves the old one as it was)
    :raises OutputError: ``out`` exists (or, with ``overwrite``, is a file), or its parent cannot be
        created or written
    """
    out = Path(out)
    if overwrite:
        _check_replaceable(out, flag)
    else:
        check_destination(out, flag)
    created = _make_parents(out, flag)
    try:
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    except OSError as error:
        _remove_empty(created)
        raise OutputError(f"{flag}: cannot write into {str(out.parent)!r}: {error.strerror or error}") from None
    try:
        with sigterm_as_interrupt():
            os.chmod(staging, 0o777 & ~_umask())  # mkdtemp makes it private; a report folder is not
            yield staging
            try:
                _publish(staging, out, flag)
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


def check_no_links(folder: str | Path, names: tuple[str, ...], flag: str = "--out") -> None:
    """Refuse a folder (e.g. a run folder handed over for ``--resume``) in which one of the entries
    that a command writes is a symbolic link: writing there would follow it out of the folder.

    :param folder: the folder
    :param names: the entries written in it (files and folders)
    :param flag: the option named in messages
    :raises OutputError: naming the link
    """
    folder = Path(folder)
    if folder.is_symlink():
        raise OutputError(f"{flag}: {str(folder)!r} is a symbolic link; give the folder itself")
    for name in names:
        if (folder / name).is_symlink():
            raise OutputError(f"{flag}: {str(folder / name)!r} is a symbolic link; a run writes only inside its folder")


def write_atomically(path: Path, write: Any) -> bool:
    """Write a file through ``write(file_object)`` into a temporary file of ``path``'s folder, then link it
    to ``path`` unless ``path`` exists (another worker's, or a user's file: never replaced).

    :return: whether ``path`` is the new file
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as file:
            write(file)
        try:
            os.link(temporary, path)  # fails if path exists: nothing is overwritten
        except FileExistsError:
            return False
        except OSError:  # a file system without hard links
            if path.exists():
                return False
            os.replace(temporary, path)
            return True
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
