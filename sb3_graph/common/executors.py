"""Where embarrassingly parallel jobs execute: local processes, a Dask cluster or Ray.

An executor runs one function over many items (a domain's evaluation harness: one run per planner and
scenario; the labelling of :mod:`sb3_graph.common.labelling`: one expert-labelled shard per sub-environment),
with one *shared* object that every call receives (the harness: the table of loaded scenarios).
The shared object travels to each worker once, never once per item:

- ``local``: this process (one worker) or a pool of spawned processes; the shared object is the
  pool initializer's argument, so each worker process unpickles it once;
- ``dask``: a ``dask.distributed`` cluster, the one at ``address`` (``--scheduler-address``) or a
  ``LocalCluster`` of ``workers`` processes with one thread each; the shared object is scattered to
  every worker once (``Client.scatter(..., broadcast=True)``) and each task gets a reference;
- ``ray``: a Ray cluster, the one at ``address`` or a local one of ``workers`` CPUs; the shared
  object is put into the object store once (``ray.put``).

The workers of a cluster must be able to import this package (``pip install sb3-graph`` on every
node), since the function is sent by reference. Results arrive in completion order, tagged with the
item's index, so the caller decides the order of its report.
"""

from __future__ import annotations

import logging
import multiprocessing
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

EXECUTORS = ("local", "dask", "ray")
# executor -> (module it needs, the pip extra that installs it)
EXTRAS = {"dask": ("distributed", "cluster"), "ray": ("ray", "ray")}

# The shared object of a local worker process (set once by the pool initializer).
_SHARED: Any = None


class ExecutorError(RuntimeError):
    """An executor cannot be used: its package is missing or its cluster cannot be reached."""


class JobExecutor(ABC):
    """Runs ``fn(item, shared)`` for every item, on some workers.

    Use it as a context manager: the workers (a pool, a cluster client) are released on exit.

    :param workers: parallel workers to start (a cluster at ``address`` brings its own)
    :param address: address of an existing cluster (``None``: start one here)
    """

    name = "?"

    def __init__(self, workers: int = 1, address: str | None = None) -> None:
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = int(workers)
        self.address = address

    @abstractmethod
    def map_unordered(
        self, fn: Callable[[Any, Any], Any], items: Sequence[Any], shared: Any
    ) -> Iterator[tuple[int, Any]]:
        """Run ``fn(item, shared)`` for every item.

        :param fn: a module-level function (workers import it by name)
        :param items: its first arguments
        :param shared: its second argument, the same for every call, sent to each worker once
        :return: ``(index of the item, result)`` pairs in the order the calls finish; the first failed
            call raises its exception (the calls not started yet are cancelled)
        """

    def describe(self) -> str:
        """The executor and its workers, for the report (e.g. ``"local, 2 processes"``)."""
        return f"{self.name}, {self.workers} worker{'s' * (self.workers != 1)}"

    def close(self) -> None:  # noqa: B027  (an executor without workers to release keeps it)
        """Release the workers (nothing to do by default)."""

    def __enter__(self) -> JobExecutor:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _init_local_worker(shared: Any) -> None:
    global _SHARED
    _SHARED = shared


def _call_with_local_shared(fn: Callable[[Any, Any], Any], item: Any) -> Any:
    return fn(item, _SHARED)


class LocalExecutor(JobExecutor):
    """This process (``workers=1``) or a pool of ``workers`` spawned processes on this machine."""

    name = "local"

    def __init__(self, workers: int = 1, address: str | None = None) -> None:
        if address is not None:
            raise ExecutorError("--scheduler-address needs --executor dask or ray (local runs on this machine)")
        super().__init__(workers)

    def describe(self) -> str:
        return "local, in this process" if self.workers == 1 else f"local, {self.workers} processes"

    def map_unordered(self, fn, items, shared):
        if self.workers == 1 or len(items) <= 1:
            for k, item in enumerate(items):
                yield k, fn(item, shared)
            return
        # spawn: workers start clean (no forked torch/matplotlib state), same on every OS
        pool = ProcessPoolExecutor(
            max_workers=min(self.workers, len(items)),
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_local_worker,
            initargs=(shared,),
        )
        try:
            futures = {pool.submit(_call_with_local_shared, fn, item): k for k, item in enumerate(items)}
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BaseException:
            # a failed call, Ctrl-C or a consumer that stopped early: do not wait for the queued calls
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()


def _import_for(executor: str):
    """Import the package an executor needs, or say which pip extra installs it."""
    import importlib

    module, extra = EXTRAS[executor]
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ExecutorError(
            f"--executor {executor} needs the {module!r} package: pip install 'sb3-graph[{extra}]'"
        ) from None


class DaskExecutor(JobExecutor):
    """A ``dask.distributed`` cluster: the one at ``address``, or a ``LocalCluster`` of ``workers``
    processes with one thread each (a run is single-threaded Python: processes are the parallelism).

    :param connect_timeout: seconds to wait for the scheduler at ``address``
    """

    name = "dask"

    def __init__(self, workers: int = 1, address: str | None = None, connect_timeout: float = 30.0) -> None:
        super().__init__(workers, address)
        distributed = _import_for("dask")
        self._cluster = None
        try:
            if address is None:
                # silence_logs: the nannies' warnings (e.g. killing a worker slow to exit at close) are noise here
                self._cluster = distributed.LocalCluster(
                    n_workers=self.workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    silence_logs=logging.ERROR,
                )
                self.client = distributed.Client(self._cluster)
            else:
                self.client = distributed.Client(address, timeout=connect_timeout)
        except (OSError, TimeoutError, ValueError) as error:
            self.close()
            if address is None:
                raise ExecutorError(f"--executor dask: cannot start a local Dask cluster ({error})") from None
            raise ExecutorError(
                f"--scheduler-address: cannot reach the Dask scheduler at {address!r} ({error})"
            ) from None

    def describe(self) -> str:
        workers = len(self.client.scheduler_info().get("workers", {}))
        where = "a local cluster" if self._cluster is not None else f"the cluster at {self.address}"
        return f"dask, {workers} worker{'s' * (workers != 1)} ({where})"

    def map_unordered(self, fn, items, shared):
        from distributed import as_completed as dask_as_completed

        # One copy per worker, referenced by every task (a list would be scattered element by element).
        [handle] = self.client.scatter([shared], broadcast=True, hash=False)
        futures = [self.client.submit(fn, item, handle, pure=False) for item in items]
        index = {future.key: k for k, future in enumerate(futures)}
        try:
            for future in dask_as_completed(futures):
                yield index[future.key], future.result()
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            self.client.cancel([handle])

    def close(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
        if self._cluster is not None:
            self._cluster.close()


class RayExecutor(JobExecutor):
    """A Ray cluster: the one at ``address`` (``ray://host:10001`` or ``auto``), or a local one with
    ``workers`` CPUs; every call is a task of one CPU."""

    name = "ray"

    def __init__(self, workers: int = 1, address: str | None = None) -> None:
        super().__init__(workers, address)
        self._ray = _import_for("ray")
        self._owner = not self._ray.is_initialized()
        if self._owner:
            try:
                if address is None:
                    self._ray.init(num_cpus=self.workers, include_dashboard=False, logging_level=logging.ERROR)
                else:
                    self._ray.init(address=address)
            except ConnectionError as error:
                raise ExecutorError(
                    f"--scheduler-address: cannot reach the Ray cluster at {address!r} ({error})"
                ) from None

    def describe(self) -> str:
        cpus = int(self._ray.cluster_resources().get("CPU", 0))
        return f"ray, {cpus} CPUs ({'a local cluster' if self.address is None else self.address})"

    def map_unordered(self, fn, items, shared):
        ray = self._ray
        handle = ray.put(shared)  # in the object store once; each task reads it from there
        task = ray.remote(num_cpus=1)(fn)
        pending = {task.remote(item, handle): k for k, item in enumerate(items)}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    yield pending.pop(ref), ray.get(ref)
        except BaseException:
            for ref in pending:
                ray.cancel(ref)
            raise

    def close(self) -> None:
        if self._owner and self._ray.is_initialized():
            self._ray.shutdown()


_CLASSES: dict[str, type[JobExecutor]] = {"local": LocalExecutor, "dask": DaskExecutor, "ray": RayExecutor}


def make_executor(name: str, workers: int = 1, address: str | None = None) -> JobExecutor:
    """The executor called ``name`` (one of :data:`EXECUTORS`).

    :param name: ``"local"``, ``"dask"`` or ``"ray"``
    :param workers: parallel workers (``--jobs``); a cluster at ``address`` brings its own
    :param address: the cluster's address (``--scheduler-address``)
    :raises ValueError: an unknown name
    :raises ExecutorError: the executor's package is missing, or its cluster cannot be reached
    """
    if name not in _CLASSES:
        raise ValueError(f"--executor: unknown executor {name!r}; expected one of {list(EXECUTORS)}")
    return _CLASSES[name](workers, address)


def check_executor(name: str, address: str | None = None) -> None:
    """Check, without starting anything, that an executor can be made (before a long run starts).

    :raises ValueError: an unknown name
    :raises ExecutorError: its package is missing, or an address is given to ``local``
    """
    if name not in _CLASSES:
        raise ValueError(f"--executor: unknown executor {name!r}; expected one of {list(EXECUTORS)}")
    if name == "local":
        if address is not None:
            raise ExecutorError("--scheduler-address needs --executor dask or ray (local runs on this machine)")
        return
    _import_for(name)
