"""The processes that search beside ``lookahead``: a pool of rollout helpers, and a search process.

- :class:`RolloutPool`: ``size - 1`` helper processes that run the rollouts of one search beside the process that
  owns the pool (which runs its share itself). Each helper is a fork of the owner's planner: its layout, its compiled
  kernels and its rollout simulation stay warm between searches; a search sends it the scene once, then one window
  tuple per rollout. The cheapest cost finished so far sits in shared memory, so that every rollout still stops as
  soon as it costs more (the exact bound of the sequential search, shared as soon as it is known).
- :class:`SearchProcess`: one process that runs whole searches (with its own rollout pool) while the steps go on;
  the planner hands it a request and reads the answer when it comes, never waiting for it.

A child ends with its parent: it reads its pipe until the pipe closes or its parent is gone. A child that dies is
seen at once (its process sentinel), so nothing waits on it: the search it served fails and the owner replaces it.
Frames on the pipes are pickles of plain values and of the planner's own objects, between a process and its
children (no user data is unpickled).
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import weakref
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np

#: how much lower the search process (and its rollout helpers, forked from it) runs than the steps (``os.nice``)
NICENESS = 10
#: seconds between two checks that a child's parent is still there while the child waits for work
_PARENT_CHECK = 0.5


class WorkerLost(RuntimeError):
    """A rollout helper or the search process ended mid-search (it is replaced; the search is void)."""


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity (macOS, Windows)
        return os.cpu_count() or 1


def check_workers(workers: object, name: str = "lookahead's workers") -> int:
    """``workers`` as an int, or a one-line error naming the parameter and its range.

    :param workers: a count of worker processes
    :param name: the parameter's name in the message
    :raises ValueError: not an integer from 1 to :func:`available_cores`
    """
    cores = available_cores()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or not 1 <= workers <= cores:
        raise ValueError(f"{name} must be an integer from 1 to {cores} (the cores available), got {workers!r}")
    return int(workers)


@contextlib.contextmanager
def _children_allowed() -> Iterator[None]:
    """``multiprocessing`` refuses children to a daemonic process, and the server's planning processes are daemonic.
    Our children end with their parent (they watch their pipe and their parent's pid), which is what the rule
    protects, so the flag is lifted while one starts."""
    me = multiprocessing.current_process()
    daemon = me._config.get("daemon")  # noqa: SLF001 (the only way to start a child from a daemonic process)
    me._config["daemon"] = False  # noqa: SLF001
    try:
        yield
    finally:
        if daemon is None:
            me._config.pop("daemon", None)  # noqa: SLF001
        else:
            me._config["daemon"] = daemon  # noqa: SLF001


def _context() -> Any:
    return multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")


def start_child(target: Callable[..., None], args: tuple, name: str) -> multiprocessing.process.BaseProcess:
    """Start ``target(*args)`` in a daemonic child process (forked where the platform can)."""
    process = _context().Process(target=target, args=args, name=name, daemon=True)
    with _children_allowed():
        process.start()
    return process


def receive(conn: Connection, parent: int) -> Any:
    """The next frame from ``conn``; ``EOFError`` once the pipe closes or the parent ``parent`` (a pid) is gone."""
    while not conn.poll(_PARENT_CHECK):
        if os.getppid() != parent:
            raise EOFError
    return conn.recv()


def _stop(processes: list, conns: list) -> None:
    """End children (a finalizer: it holds no reference to its owner)."""
    for conn in conns:
        with contextlib.suppress(OSError):
            conn.close()
    for process in processes:
        if process is not None and process.is_alive():
            process.kill()
    for process in processes:
        if process is not None:
            process.join(timeout=1.0)


# ---------------------------------------------------------------------------------------------------- rollouts
def _helper_main(planner: Any, conn: Connection, parent: int, bound: Any, layout: Any) -> None:
    """A rollout helper: ``("scene", layout_key, layout | None, scene, memory, stopped)`` sets what the next
    rollouts start from; ``("rollout", index, windows)`` answers ``(index, cost)``."""
    shared = np.frombuffer(bound, dtype=float)
    layouts: dict[int, Any] = {id(layout): layout}
    scene = None
    planner._pool = None  # noqa: SLF001 (a helper runs its rollouts itself)
    try:
        while True:
            message = receive(conn, parent)
            if message[0] == "scene":
                _, key, layout, scene, memory, stopped = message
                if layout is not None:
                    layouts[key] = layout
                scene = dataclasses.replace(scene, layout=layouts[key])
                planner.adopt_memory(memory, stopped)
            else:
                _, index, windows = message
                steps = planner.rollout_steps
                cost = planner.rollout(scene, np.array(windows, dtype=float), bound=float(shared[0]), shared=shared)
                conn.send((index, cost, planner.rollout_steps - steps))
    except (EOFError, OSError, KeyboardInterrupt):
        return


class RolloutPool:
    """``size - 1`` helper processes for the rollouts of the searches of ``planner`` (which runs its share itself).

    :param planner: the :class:`~envs.planners.lookahead.LookaheadPlanner` that searches (each helper is a fork)
    :param size: processes running rollouts in all, the owner's included (>= 2)
    :param layout: the layout of the first search (the helpers hold it from the start)
    """

    def __init__(self, planner: Any, size: int, layout: Any) -> None:
        self.size = int(size)
        self.restarts = 0
        self._bound = _context().RawArray("d", 1)
        self.shared = np.frombuffer(self._bound, dtype=float)
        self._helpers: list[Any] = [None] * (self.size - 1)
        self._conns: list[Connection | None] = [None] * (self.size - 1)
        self._sent: list[set] = [set() for _ in self._helpers]  # layout keys each helper holds
        for k in range(self.size - 1):
            self._spawn(planner, k, layout)
        self._finalizer = weakref.finalize(self, _stop, self._helpers, self._conns)

    def _spawn(self, planner: Any, k: int, layout: Any) -> None:
        here, there = _context().Pipe()
        args = (planner, there, os.getpid(), self._bound, layout)
        self._helpers[k] = start_child(_helper_main, args, f"lookahead-rollouts-{k}")
        there.close()
        self._conns[k], self._sent[k] = here, {id(layout)}

    def close(self) -> None:
        """End the helpers."""
        self._finalizer()

    def alive(self) -> bool:
        return all(p is not None and p.is_alive() for p in self._helpers)

    def replace_dead(self, planner: Any, layout: Any) -> None:
        """Replace the helpers that ended, and every other one (their answers to the void search are still due)."""
        self.restarts += sum(1 for p in self._helpers if p is not None and not p.is_alive())
        _stop(list(self._helpers), [c for c in self._conns if c is not None])
        for k in range(self.size - 1):
            self._spawn(planner, k, layout)
        self._finalizer.detach()
        self._finalizer = weakref.finalize(self, _stop, self._helpers, self._conns)

    def costs(
        self, planner: Any, scene: Any, tasks: list[tuple[Any, tuple[float, ...]]], bound: float
    ) -> dict[Any, float]:
        """The cost of each task's windows, over the helpers and the owner, every rollout stopped once it costs
        more than the cheapest finished (or than ``bound``).

        :param planner: the owner (it runs its share of the rollouts)
        :param scene: the scene the rollouts start from
        :param tasks: ``(key, windows per road)`` pairs
        :param bound: the cheapest cost known before these tasks
        :return: ``key -> cost``
        :raises WorkerLost: a helper ended (the caller replaces them with :meth:`replace_dead`)
        """
        self.shared[0] = bound
        queue = list(enumerate(tasks))
        results: dict[Any, float] = {}
        busy: dict[int, int] = {}  # helper -> task index
        told: set[int] = set()
        work = [0] * self.size  # rollout steps per process (the owner last)

        def settle(index: int, cost: float) -> None:
            results[tasks[index][0]] = cost
            self.shared[0] = min(self.shared[0], cost)

        while queue or busy:
            for k, conn in enumerate(self._conns):  # every idle helper takes the next task
                if not queue:
                    break
                if k in busy:
                    continue
                if k not in told:
                    self._tell(planner, scene, k)
                    told.add(k)
                index, (_, windows) = queue.pop(0)
                conn.send(("rollout", index, windows))
                busy[k] = index
            if queue:  # the owner's share
                index, (_, windows) = queue.pop(0)
                steps = planner.rollout_steps
                cost = planner.rollout(scene, np.array(windows), bound=float(self.shared[0]), shared=self.shared)
                work[-1] += planner.rollout_steps - steps
                settle(index, cost)
                ready = [c for c in self._conns if c.poll()]
            else:
                sentinels = [self._helpers[k].sentinel for k in busy]
                ready = wait([self._conns[k] for k in busy] + sentinels)
            for k in list(busy):
                conn = self._conns[k]
                if conn in ready or conn.poll():
                    try:
                        index, cost, steps = conn.recv()
                    except (EOFError, OSError) as error:
                        raise WorkerLost(f"rollout helper {k} ended mid-search") from error
                    settle(index, cost)
                    planner.rollouts += 1  # the owner counts its own in its rollouts
                    planner.rollout_steps += steps
                    work[k] += steps
                    del busy[k]
                elif not self._helpers[k].is_alive():
                    raise WorkerLost(f"rollout helper {k} ended mid-search")
        planner.critical_steps += max(work)
        return results

    def _tell(self, planner: Any, scene: Any, k: int) -> None:
        """Send helper ``k`` the scene of this search (its layout only the first time)."""
        layout, key = scene.layout, id(scene.layout)
        memory, stopped = planner.memory()
        first = key not in self._sent[k]
        self._conns[k].send(("scene", key, layout if first else None, dataclasses.replace(scene, layout=None), memory,
                             stopped))  # fmt: skip
        self._sent[k].add(key)


def lower_priority() -> bool:
    """Run this process (and the children it forks) :data:`NICENESS` lower than the steps (``os.nice``): a waking
    step takes the core from it. Not the idle scheduling class (``SCHED_IDLE``): on a loaded machine it starved the
    search (no answer in 60 steps of a test at load 9 on 2 cores), where nice 10 still gets about a tenth of a core;
    served at 100 vehicles at load 5-6 on 2 cores it made the steps no faster (p50 1.09x and 1.15x of glide+shield's
    against 1.11x at nice 10, ``benchmarks/bench_serve_lookahead.py --steps 300``) and its searches fewer and older
    (20 and 21 against 27 in 60 s, windows 1.6 and 1.9 s old on average against 1.4 s): a step of lookahead costs
    what its CPU costs, not a wait for a core.
    Returns whether it could (no ``os.nice`` on Windows)."""
    try:
        os.nice(NICENESS)
    except (OSError, AttributeError):
        return False
    return True


# ---------------------------------------------------------------------------------------------------- searches
def _search_main(searcher: Any, conn: Connection, parent: int, layout: Any) -> None:
    """The search process: each request ``(generation, scene, memory, road_windows, proposed, steps)`` is answered
    ``(generation, predicted time, result, counters added)`` (:meth:`LookaheadPlanner.search_ahead`)."""
    layouts: dict[int, Any] = {id(layout): layout}
    lower_priority()
    try:
        while True:
            generation, key, sent, scene, memory, road_windows, proposed, steps = receive(conn, parent)
            if sent is not None:
                layouts[key] = sent
            scene = dataclasses.replace(scene, layout=layouts[key])
            searcher.adopt_memory(*memory)
            before = searcher.counters()
            searched_at, result = searcher.search_ahead(scene, road_windows, proposed, steps)
            after = searcher.counters()
            conn.send((generation, searched_at, result, {k: v - before[k] for k, v in after.items()}))
    except (EOFError, OSError, KeyboardInterrupt):
        return
    finally:
        searcher.close()


class SearchProcess:
    """A process that runs whole searches of ``searcher`` (a synchronous ``lookahead``, with its own rollout pool)
    while the steps go on: :meth:`submit` a request, :meth:`poll` for the answer without waiting.

    :param searcher: the planner whose searches run there (forked: its layout and kernels come warm)
    :param layout: the layout of the first request (the process holds it from the start)
    """

    def __init__(self, searcher: Any, layout: Any) -> None:
        here, there = _context().Pipe()
        self.process = start_child(_search_main, (searcher, there, os.getpid(), layout), "lookahead-search")
        there.close()
        self.conn = here
        self._sent = {id(layout)}
        self._finalizer = weakref.finalize(self, _stop, [self.process], [self.conn])

    def submit(self, request: tuple) -> None:
        """Start a search: ``(generation, scene, memory, road_windows, proposed, steps)`` (one at a time)."""
        generation, scene, *rest = request
        key = id(scene.layout)
        sent = None if key in self._sent else scene.layout
        self.conn.send((generation, key, sent, dataclasses.replace(scene, layout=None), *rest))
        self._sent.add(key)

    def poll(self) -> tuple | None:
        """The answer of the search submitted, or ``None`` while it runs.

        :raises WorkerLost: the process ended
        """
        try:
            if self.conn.poll():
                return self.conn.recv()
        except (EOFError, OSError) as error:
            raise WorkerLost("the search process ended mid-search") from error
        if not self.process.is_alive():
            raise WorkerLost("the search process ended mid-search")
        return None

    def close(self) -> None:
        """End the process."""
        self._finalizer()
