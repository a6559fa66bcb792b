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

Every form records a heartbeat of each running trial: the trial of a worker that was killed is
marked ``FAIL`` once its heartbeat is older than the grace period, the next time any worker asks
for a trial, so the study goes on (optionally the failed trial is retried with the same
parameters). The databases use Optuna's own heartbeat table; Optuna's journal storage has none, so
:class:`HeartbeatJournalStorage` keeps the heartbeat as a trial system attribute in the journal.
"""

from __future__ import annotations

import importlib.util
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
) -> BaseStorage:
    """Open (and create if needed) the Optuna storage a URL names.

    :param url: one of :data:`ACCEPTED_FORMS`
    :param heartbeat_interval: seconds between heartbeats of a running trial
    :param grace_period: seconds without heartbeat after which a running trial is failed
        (default: twice the interval)
    :param max_retry: how often a trial failed that way is retried with the same parameters (0: none)
    :return: the storage
    :raises StorageURLError: an unsupported URL, or PostgreSQL without its driver
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
        _make_folder(path.parent, url)
        # The open()-based lock works on file systems without symlinks (and on most NFS setups).
        backend = JournalFileBackend(str(path), lock_obj=JournalFileOpenLock(str(path)))
        grace = grace_period if grace_period is not None else 2 * int(heartbeat_interval)
        return HeartbeatJournalStorage(backend, int(heartbeat_interval), grace, callback)
    if kind == "sqlite":
        _make_folder(sqlite_path(url).parent, url)
        engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT_S}}
    else:
        url = postgres_driver_url(url)
        engine_kwargs = {"pool_pre_ping": True}
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
