"""Storage URLs -> Optuna storages: one machine (SQLite) or many workers (PostgreSQL, journal file).

Accepted forms (:data:`ACCEPTED_FORMS`):

- ``sqlite:///relative/path.db`` or ``sqlite:////absolute/path.db``: an embedded database file,
  nothing to start; its folder is created. Suits the worker processes of one machine.
- ``postgresql://user:password@host:port/database`` (also ``postgresql+psycopg2://``): a shared
  server, for workers on many machines (needs the ``psycopg2-binary`` package:
  ``pip install "sb3-graph[postgres]"``).
- ``journal://PATH``: an Optuna journal file (``JournalStorage`` + ``JournalFileBackend``) on a
  shared disk; everything after ``journal://`` is the path, so ``journal:///mnt/shared/study.log``
  is absolute and ``journal://studies/study.log`` relative. Its folder is created.

A storage is often a file or a server that holds other things too, so :func:`make_storage` checks
before it writes: a read-only command (``tune-report``, ``read_only=True``) never creates tables
or files, and refuses a database without Optuna's tables; ``tune`` refuses a database that holds
tables of another application, or a file that is not an Optuna journal, unless ``allow_foreign``
(``--allow-foreign-storage``). A PostgreSQL server gets :data:`CONNECT_TIMEOUT_S` to answer and
each statement :data:`STATEMENT_TIMEOUT_S`; SQLite waits :data:`SQLITE_TIMEOUT_S` for a lock.

Every form records a heartbeat of each running trial: the trial of a worker that was killed is
marked ``FAIL`` once its heartbeat is older than the grace period, the next time any worker asks
for a trial, so the study goes on (optionally the failed trial is retried with the same
parameters). The databases use Optuna's own heartbeat table; Optuna's journal storage has none, so
:class:`HeartbeatJournalStorage` keeps the heartbeat as a trial system attribute in the journal.
"""

from __future__ import annotations

import importlib.util
import json
import re
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import optuna
import sqlalchemy.exc
from optuna.storages import BaseStorage, JournalStorage, RDBStorage, RetryHeartbeatStaleTrialCallback
from optuna.storages._heartbeat import BaseHeartbeat
from optuna.storages.journal import BaseJournalBackend, JournalFileBackend, JournalFileOpenLock
from optuna.trial import FrozenTrial, TrialState

ACCEPTED_FORMS = (
    "sqlite:///PATH.db",
    "postgresql://USER:PASSWORD@HOST:PORT/DATABASE",
    "journal://PATH (journal:///ABSOLUTE/PATH.log)",
)
DEFAULT_HEARTBEAT_S = 60
# SQLite: wait for a lock held by another worker process instead of failing at once.
SQLITE_TIMEOUT_S = 60.0
# PostgreSQL: a server that accepts and never answers fails the command after this many seconds.
CONNECT_TIMEOUT_S = 10
# PostgreSQL: longest statement (Optuna's are short; a locked table or a stalled server is not).
STATEMENT_TIMEOUT_S = 120
# Longest first line of a journal file read to check that it is one.
JOURNAL_PROBE_BYTES = 1 << 20
FOREIGN_HINT = "pass --allow-foreign-storage to use it anyway"


class StorageURLError(ValueError):
    """A storage URL that is none of the accepted forms."""


# Attempts after a lost race to create the schema of a fresh database.
SCHEMA_RACE_RETRIES = 5
# Trial system attribute holding the time (Unix seconds) of a journal trial's last heartbeat.
JOURNAL_HEARTBEAT_ATTR = "sb3_graph:heartbeat"


class HeartbeatJournalStorage(JournalStorage, BaseHeartbeat):
    """Optuna's ``JournalStorage`` with the heartbeat that Optuna gives only to ``RDBStorage``.

    A running trial's heartbeat is a system attribute (:data:`JOURNAL_HEARTBEAT_ATTR`) rewritten
    every ``heartbeat_interval`` seconds; Optuna fails a running trial whose heartbeat (or, before
    the first one, its start) is older than ``grace_period`` before it starts the next trial.

    :param backend: the journal backend (e.g. a ``JournalFileBackend``)
    :param heartbeat_interval: seconds between heartbeats
    :param grace_period: seconds without heartbeat after which a running trial counts as dead
    :param heartbeat_stale_trial_callback: called with each trial failed that way
    """

    def __init__(
        self,
        backend: BaseJournalBackend,
        heartbeat_interval: int,
        grace_period: int,
        heartbeat_stale_trial_callback: Callable[[optuna.Study, FrozenTrial], None] | None = None,
    ) -> None:
        super().__init__(backend)
        self._heartbeat_interval = heartbeat_interval
        self._grace_period = grace_period
        self._stale_trial_callback = heartbeat_stale_trial_callback

    def record_heartbeat(self, trial_id: int) -> None:
        self.set_trial_system_attr(trial_id, JOURNAL_HEARTBEAT_ATTR, time.time())

    def _get_stale_trial_ids(self, study_id: int) -> list[int]:
        now = time.time()
        running = self.get_all_trials(study_id, deepcopy=False, states=(TrialState.RUNNING,))
        return [
            t._trial_id
            for t in running
            if now - t.system_attrs.get(JOURNAL_HEARTBEAT_ATTR, t.datetime_start.timestamp()) > self._grace_period
        ]

    def get_heartbeat_interval(self) -> int:
        return self._heartbeat_interval

    def get_heartbeat_stale_trial_callback(self) -> Callable[[optuna.Study, FrozenTrial], None] | None:
        return self._stale_trial_callback


def storage_kind(url: str) -> str:
    """Which kind of storage a URL names.

    :param url: storage URL
    :return: ``"sqlite"``, ``"postgresql"`` or ``"journal"``
    :raises StorageURLError: any other form, naming the accepted ones
    """
    if not isinstance(url, str) or not url.strip():
        raise StorageURLError(f"storage URL must be a non-empty string; accepted forms: {', '.join(ACCEPTED_FORMS)}")
    if url.startswith("sqlite:///") and len(url) > len("sqlite:///"):
        return "sqlite"
    if re.match(r"^postgres(ql)?(\+\w+)?://[^/]+/\w", url):
        return "postgresql"
    if url.startswith("journal://") and len(url) > len("journal://"):
        return "journal"
    raise StorageURLError(f"storage URL {redact(url)!r} is not supported; accepted forms: {', '.join(ACCEPTED_FORMS)}")


def redact(url: str) -> str:
    """The URL with its password replaced by ``***`` (for messages and logs)."""
    return re.sub(r"(://[^:/@]+:)[^@]*@", r"\1***@", str(url))


def sqlite_path(url: str) -> Path:
    """The database file of an ``sqlite:///`` URL."""
    return Path(url[len("sqlite:///") :])


def make_storage(
    url: str,
    heartbeat_interval: int = DEFAULT_HEARTBEAT_S,
    grace_period: int | None = None,
    max_retry: int = 0,
    read_only: bool = False,
    allow_foreign: bool = False,
) -> BaseStorage:
    """Open (and create if needed) the Optuna storage a URL names.

    :param url: one of :data:`ACCEPTED_FORMS`
    :param heartbeat_interval: seconds between heartbeats of a running trial
    :param grace_period: seconds without heartbeat after which a running trial is failed
        (default: twice the interval)
    :param max_retry: how often a trial failed that way is retried with the same parameters (0: none)
    :param read_only: the caller only reads: nothing is created (no folder, table or file), and a
        storage without Optuna's tables is refused
    :param allow_foreign: use a database that holds other tables, or a file that is not a journal
    :return: the storage
    :raises StorageURLError: an unsupported URL, PostgreSQL without its driver, or a storage
        refused as above
    """
    kind = storage_kind(url)
    if heartbeat_interval < 1:
        raise ValueError(f"heartbeat_interval must be a positive number of seconds, got {heartbeat_interval}")
    callback = None
    if max_retry > 0:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            callback = RetryHeartbeatStaleTrialCallback(max_retry=max_retry)
    if kind == "journal":
        path = Path(url[len("journal://") :])
        _check_journal(path, url, read_only, allow_foreign)
        _make_folder(path.parent, url)
        # The open()-based lock works on file systems without symlinks (and on most NFS setups).
        backend = JournalFileBackend(str(path), lock_obj=JournalFileOpenLock(str(path)))
        grace = grace_period if grace_period is not None else 2 * int(heartbeat_interval)
        return HeartbeatJournalStorage(backend, int(heartbeat_interval), grace, callback)
    if kind == "sqlite":
        if read_only and not sqlite_path(url).is_file():
            raise StorageURLError(f"database file {str(sqlite_path(url))!r} does not exist")
        _check_regular(sqlite_path(url), url)
        if not read_only:
            _make_folder(sqlite_path(url).parent, url)
        engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT_S}}
    else:
        url = postgres_driver_url(url)
        engine_kwargs = {
            "pool_pre_ping": True,
            "connect_args": {
                "connect_timeout": CONNECT_TIMEOUT_S,
                "options": f"-c statement_timeout={STATEMENT_TIMEOUT_S * 1000}",
                "keepalives": 1,
                "keepalives_idle": CONNECT_TIMEOUT_S,
                "keepalives_interval": 5,
                "keepalives_count": 3,
            },
        }
    _check_tables(url, engine_kwargs, read_only, allow_foreign)
    with warnings.catch_warnings():  # heartbeats are "experimental" in Optuna, but documented and used here
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        for attempt in range(SCHEMA_RACE_RETRIES + 1):
            try:
                return RDBStorage(
                    url,
                    engine_kwargs=engine_kwargs,
                    heartbeat_interval=int(heartbeat_interval),
                    grace_period=grace_period,
                    heartbeat_stale_trial_callback=callback,
                    skip_table_creation=read_only,
                )
            except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
                # Workers that start together on a fresh database race to create Optuna's tables;
                # the loser sees a duplicate type or table and succeeds once the winner is done.
                if attempt == SCHEMA_RACE_RETRIES:
                    raise
                time.sleep(0.5 * (attempt + 1))
            except sqlalchemy.exc.SQLAlchemyError as error:  # unreachable server, bad password, missing database
                first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
                raise StorageURLError(f"cannot open storage {redact(url)!r}: {first}") from error
    raise AssertionError("unreachable")


def optuna_tables() -> set[str]:
    """The tables that Optuna's RDB storage creates (its models and alembic's version table)."""
    from optuna.storages._rdb import models

    return set(models.BaseModel.metadata.tables) | {"alembic_version"}


def _check_tables(url: str, engine_kwargs: dict, read_only: bool, allow_foreign: bool) -> None:
    """Look at a database's tables before Optuna creates its own (see the module docstring)."""
    try:
        engine = sqlalchemy.create_engine(url, **engine_kwargs)
        try:
            tables = set(sqlalchemy.inspect(engine).get_table_names())
        finally:
            engine.dispose()
    except sqlalchemy.exc.SQLAlchemyError as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise StorageURLError(f"cannot open storage {redact(url)!r}: {first}") from error
    ours = optuna_tables()
    foreign = sorted(name for name in tables - ours if not name.startswith("sqlite_"))
    if read_only and not {"studies", "version_info", "alembic_version"} <= tables:
        raise StorageURLError(
            f"storage {redact(url)!r} holds no Optuna study (tables: {foreign[:8] or 'none'}); "
            "a read-only command creates none"
        )
    if foreign and not read_only and not allow_foreign:
        raise StorageURLError(
            f"storage {redact(url)!r} holds tables of another application ({', '.join(foreign[:8])}); "
            f"Optuna would add its own there; {FOREIGN_HINT}"
        )


def _check_regular(path: Path, url: str) -> None:
    if path.exists() and not path.is_file():
        raise StorageURLError(f"storage {redact(url)!r}: {str(path)!r} is not a regular file")


def _check_journal(path: Path, url: str, read_only: bool, allow_foreign: bool) -> None:
    """A journal file is a regular file whose lines are Optuna's JSON operations (an empty or new one too)."""
    if read_only and not path.is_file():
        raise StorageURLError(f"journal file {str(path)!r} does not exist")
    _check_regular(path, url)
    if not path.is_file() or path.stat().st_size == 0:
        return
    with open(path, "rb") as file:
        first = file.readline(JOURNAL_PROBE_BYTES)
    try:
        operation = json.loads(first)
    except (ValueError, RecursionError):
        operation = None
    if not isinstance(operation, dict) or "op_code" not in operation:
        hint = "" if read_only else f"; {FOREIGN_HINT}"
        if read_only or not allow_foreign:
            raise StorageURLError(f"{str(path)!r} is not an Optuna journal file (its first line is not one){hint}")


def _make_folder(folder: Path, url: str) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise StorageURLError(
            f"cannot open storage {redact(url)!r}: cannot create folder {str(folder)!r} ({error.strerror or error})"
        ) from None


def postgres_driver_url(url: str) -> str:
    """A PostgreSQL URL with an installed driver named (SQLAlchemy 2.1 assumes psycopg 3 otherwise).

    :param url: ``postgres[ql][+driver]://...``
    :return: ``postgresql+psycopg2://...`` or ``postgresql+psycopg://...`` (a named driver is kept)
    :raises StorageURLError: neither driver is installed
    """
    scheme, rest = url.split("://", 1)
    if "+" in scheme:
        return f"postgresql+{scheme.split('+', 1)[1]}://{rest}"
    for driver in ("psycopg2", "psycopg"):
        if importlib.util.find_spec(driver) is not None:
            return f"postgresql+{driver}://{rest}"
    raise StorageURLError('PostgreSQL storage needs a driver: pip install "sb3-graph[postgres]" (psycopg2-binary)')
