"""A search by rollouts over glide's advice (``lookahead``): the planner that looks ahead.

Every planner that decides from the scene now sits on a stops-for-delay front; a search that rolls the
scene forward in the project's own simulation leaves it. Every ``period`` seconds ``lookahead``:

1. copies the scene into a :class:`~envs.simulation.engine.Simulation` (no new arrivals: a vehicle that
   appears within the horizon is 80 m out and rarely meets the vehicles planned now, and drawn arrivals
   would make the search's choice depend on a draw);
2. for each candidate advice window (:class:`~envs.planners.glide.GlidePlanner`'s ``window``, the same
   for every vehicle), drives ``horizon`` seconds with glide on that window behind a fresh shield;
3. with ``per_approach`` (the default), then tries each other candidate on one approach road at a time (a
   greedy pass; the others keep their best), so that the major road can be advised while the minor one races;
4. keeps the candidate with the lowest cost: the seconds lost against each vehicle's lane limit over the
   horizon, plus ``stop_price`` seconds per vehicle that comes to a stop in it (below 0.3 m/s, the
   metrics' threshold; a vehicle already stopped once is not counted again), plus ``energy_price``
   seconds per kJ of traction energy; with a ``proposer`` (an advice policy), its own windows per vehicle
   are one more candidate (expert iteration: the network proposes, the search keeps what costs least).

Between searches each vehicle is advised with its approach road's window of the last search, even one
that was advised on a wider window before (with ``hold``, advice once given holds to the line instead,
glide's rule for a policy's windows: the search then changes only the vehicles not yet advised; it saves
less delay). A search that runs
out of its wall-time ``budget`` keeps glide's own window for that period and is counted
(``lookahead_fallbacks`` in the run's stats). The shield checks the real step as for any planner:
``lookahead`` is meant to run behind it (``lookahead+shield``).

A search runs in the step that starts it (``mode="sync"``, the default), or beside the steps from the scene predicted
to when its windows will apply (``"async"``): emulated deterministically in simulated time (``clock="steps"``, for
evaluation), or truly concurrent in a process of its own (``clock="wall"``, the server's). One search's rollouts run
over ``workers`` processes (:mod:`envs.planners.search_workers`).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, fields, replace

import numpy as np

from envs.planners import _shield_kernel
from envs.planners.glide import RECIPE, GlideParams, GlidePlanner
from envs.planners.priority import PriorityPlanner
from envs.planners.search_workers import (
    RolloutPool,
    SearchProcess,
    WorkerLost,
    available_cores,
    check_workers,
)
from envs.planners.shield import Shield, envelope_table
from envs.simulation.engine import Simulation
from envs.simulation.motion import traction_energy
from envs.simulation.scene import STOP_SPEED, Scene

#: How a search runs against the steps (:class:`LookaheadParams`' ``mode``).
MODES = ("sync", "async")
#: Whose time an ``"async"`` search's latency runs on (:class:`LookaheadParams`' ``clock``).
CLOCKS = ("steps", "wall")


@dataclass(frozen=True)
class LookaheadParams:
    """Free parameters of :class:`LookaheadPlanner`.

    :param windows: the candidate advice windows [m], each >= 0 (``inf``: the whole approach)
    :param horizon: seconds each rollout drives ahead, > 0
    :param period: seconds between two searches, > 0 (rounded to whole policy steps, at least one)
    :param stop_price: seconds of delay that one new stop costs, >= 0
    :param energy_price: seconds of delay that one kJ of traction energy costs, >= 0
    :param per_approach: after the global choice, a greedy pass over the approach roads (default; it costs about
        4x the search of one window for all roads, and leaves less delay, fewer stops and more flow at every
        demand from 0.05 to 0.8 veh/s per major lane: docs/baselines.md)
    :param budget: wall seconds a search may take, > 0 (``inf``: no limit); past it glide's own window
    :param step_budget: vehicle-steps that a search's critical path may plan per second of its period, > 0 (``inf``:
        no limit). A rollout step of n vehicles counts n; each wave of rollouts is planned at its most (its rounds
        over the workers x the horizon's steps x the vehicles now), so the cut is deterministic. A wave that would
        pass the budget is cut: the flat windows keep their first candidates (the last search's windows first),
        the greedy pass takes the roads with the most vehicles before their line first, and roads not reached keep
        their best so far. Default 14,000: a 30-vehicle search of one process fits whole; at 100 vehicles two
        workers run the flat windows and one road (docs/speed.md)
    :param rollout_frequency: decisions per second inside a rollout [Hz], a divisor of the simulation's 15 Hz
        (5: as the real planner; 3 plans 40 % fewer steps, and the real step's shield still guards)
    :param shield_horizon: the rollouts' shield predicts this many seconds ahead, > 0 (the real shield: 8)
    :param hold: advice once given holds to the line (glide's rule for a policy's windows), so a search changes
        only the vehicles not yet advised; ``False`` (default): every vehicle follows its road's window of the
        last search (on the main job's first 30 scenarios: +0.018 veh/s and -0.8 s against holding)
    :param mode: ``"sync"`` (default): a search runs in the step that starts it, which waits for it; ``"async"``: a
        search runs beside the steps, from the scene predicted ``latency`` ahead, and every step answers at glide's
        cost from the windows of the latest finished search
    :param clock: whose time an ``"async"`` search takes: ``"steps"`` (default), emulated deterministically in
        simulated time (the search runs in the step that starts it, and its windows land exactly ``latency``
        later: what the search process gives when no search is late; reproducible, for evaluation); ``"wall"``:
        truly concurrent, in a process beside the steps (the server's), its windows applied when they come (a
        search late by the horizon or more is dropped, and windows older than the horizon give way to glide's own)
    :param latency: seconds from an ``"async"`` search's start until its windows apply, > 0 (``None``: the period,
        and on the ``"wall"`` clock at least the wall time that the last searches took, counted in the wall time
        between steps, at most the horizon); rounded to whole policy steps, at least one
    :param workers: processes that run one search's rollouts, from 1 to the cores available (``None``: on the
        ``"wall"`` clock the cores but one, which the steps keep, at least 1; otherwise 1, since an evaluation
        already runs its runs in parallel)
    """

    windows: tuple[float, ...] = (0.0, 30.0, math.inf)
    horizon: float = 8.0
    period: float = 1.0
    stop_price: float = 2.0
    energy_price: float = 0.0
    per_approach: bool = True
    budget: float = math.inf
    step_budget: float = 14000.0
    rollout_frequency: int = 5
    shield_horizon: float = 8.0
    hold: bool = False
    mode: str = "sync"
    clock: str = "steps"
    latency: float | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        windows = self.windows
        if not (isinstance(windows, (tuple, list)) and windows and all(_number(w) and w >= 0 for w in windows)):
            raise ValueError(
                f"lookahead's windows must be a non-empty list of numbers >= 0 (inf allowed), got {windows!r}"
            )
        object.__setattr__(self, "windows", tuple(float(w) for w in windows))
        rules = {
            "horizon": ("a finite number > 0", lambda x: _number(x) and 0 < x < math.inf),
            "period": ("a finite number > 0", lambda x: _number(x) and 0 < x < math.inf),
            "stop_price": ("a finite number >= 0", lambda x: _number(x) and 0 <= x < math.inf),
            "energy_price": ("a finite number >= 0", lambda x: _number(x) and 0 <= x < math.inf),
            "per_approach": ("true or false", lambda x: isinstance(x, bool)),
            "hold": ("true or false", lambda x: isinstance(x, bool)),
            "budget": ("a number > 0 (inf: no limit)", lambda x: _number(x) and x > 0),
            "step_budget": ("a number > 0 (inf: no limit)", lambda x: _number(x) and x > 0),
            "rollout_frequency": ("one of [1, 3, 5, 15]", lambda x: x in (1, 3, 5, 15) and not isinstance(x, bool)),
            "shield_horizon": ("a finite number > 0", lambda x: _number(x) and 0 < x < math.inf),
            "mode": (f"one of {list(MODES)}", lambda x: x in MODES),
            "clock": (f"one of {list(CLOCKS)}", lambda x: x in CLOCKS),
            "latency": ("a finite number > 0 or None (the period)",
                        lambda x: x is None or (_number(x) and 0 < x < math.inf)),
        }  # fmt: skip
        for field in fields(self):
            if field.name in rules and not rules[field.name][1](getattr(self, field.name)):
                raise ValueError(
                    f"lookahead's {field.name} must be {rules[field.name][0]}, got {getattr(self, field.name)!r}"
                )
        if self.workers is not None:
            object.__setattr__(self, "workers", check_workers(self.workers))

    @property
    def processes(self) -> int:
        """The processes that run one search's rollouts (``workers``, or its default for the mode)."""
        if self.workers is not None:
            return self.workers
        return max(1, available_cores() - 1) if self.mode == "async" and self.clock == "wall" else 1


def _number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and not math.isnan(x)


class LookaheadPlanner(GlidePlanner):
    """glide whose advice window per approach road is chosen by rollouts in the simulation (see the module docstring).

    :param name: the name shown in reports
    :param params: the search's parameters
    :param glide: glide's parameters (its ``window`` is the fallback of a search past its budget; default
        :data:`~envs.planners.glide.RECIPE`, over which the search saves more delay than over the tuned values)
    :param proposer: an ``"advice"`` policy over glide (:class:`~envs.planners.priority.PriorityPlanner`) whose
        windows for the vehicles now are one more candidate of every search (expert iteration: the network
        proposes, the search keeps its proposal where it costs least); ``None``: the windows per road alone
    """

    def __init__(
        self,
        name: str = "Lookahead",
        params: LookaheadParams | None = None,
        glide: GlideParams | None = None,
        proposer: PriorityPlanner | None = None,
    ) -> None:
        if proposer is not None and getattr(proposer, "kind", None) != "advice":
            name = getattr(proposer, "name", proposer)
            raise ValueError(f"lookahead's proposer must be an 'advice' policy over glide, got {name!r}")
        self.search = params if params is not None else LookaheadParams()
        self.proposer = proposer
        super().__init__(name, glide if glide is not None else RECIPE, hold=self.search.hold)

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self._road_windows: np.ndarray | None = None  # (roads,) windows of the last search
        self._proposed: tuple[np.ndarray, np.ndarray] | None = None  # (ids, windows) when the proposal won
        self.proposals_kept = 0
        if self.proposer is not None:
            self.proposer.reset(seed)
        self._stopped = np.zeros(0, np.int64)  # ids that have stopped (sorted)
        self._steps = 0
        self._sim: Simulation | None = None
        self._predictor: Simulation | None = None
        self.searches = self.fallbacks = self.rollouts = self.shrunk = 0
        self.search_seconds = 0.0
        # Rollout steps run, and those on the critical path (the longest process's share, wave by wave): the
        # wall time of a search on idle cores, in rollout steps.
        self.rollout_steps = self.critical_steps = 0
        # The search beside the steps: a search's answer is matched to the episode that asked for it.
        self._generation = getattr(self, "_generation", 0) + 1
        if self.search.clock == "steps":
            self._inflight: dict | None = None
        self._next_launch = 0
        self._windows_time: float | None = None  # the (predicted) scene time the windows in force were searched at
        self.started = self.applied = self.late = self.dropped = self.mismatched = self.expired = 0
        self.worker_restarts = 0
        self._age_sum, self._age_max, self._age_steps = 0.0, 0.0, 0
        self._ahead_sum = 0.0  # seconds ahead that the searches started were predicted, summed
        self._search_walls: list[float] = getattr(self, "_search_walls", [])  # wall s of the last searches
        self._step_wall: float | None = None  # wall s between two steps (a moving average)
        self._last_step: float | None = None

    def stats(self) -> dict[str, float]:
        """Searches, the ones that ran out of budget, rollouts and wall seconds spent searching; beside the steps
        (``"async"``), searches started, applied, late (applied or not), dropped (a horizon late, or their
        worker lost), mismatched (the scene changed: a reset, another layout), windows expired (older than the
        horizon: glide's own window until the next answer), replaced workers, the mean and
        largest age of the windows in force [s of scene time since the scene they were searched for], and how far
        ahead the searches were predicted on average [s]."""
        stats = {
            "lookahead_searches": self.searches,
            "lookahead_fallbacks": self.fallbacks,
            "lookahead_shrunk": self.shrunk,
            "lookahead_rollouts": self.rollouts,
            "lookahead_search_s": self.search_seconds,
        }
        if self.proposer is not None:
            stats["lookahead_proposals_kept"] = self.proposals_kept
        if self.search.mode != "sync":
            stats.update(
                lookahead_started=self.started,
                lookahead_applied=self.applied,
                lookahead_late=self.late,
                lookahead_dropped=self.dropped,
                lookahead_mismatched=self.mismatched,
                lookahead_expired=self.expired,
                lookahead_age_s=self._age_sum / max(self._age_steps, 1),
                lookahead_age_s_max=self._age_max,
                lookahead_ahead_s=self._ahead_sum / max(self.started, 1),
            )
        if self.search.mode != "sync" or self.search.processes > 1:
            stats["lookahead_worker_restarts"] = self.worker_restarts
        return stats

    def beside_the_steps(self, mode: str = "async", workers: int | None = None) -> None:
        """Search as the server runs it from now on: beside the steps, truly concurrently (``mode="async"``,
        ``clock="wall"``; the default), or in the step that asks (``"sync"``). Resets the planner.

        :param mode: one of :data:`MODES`
        :param workers: processes per search, from 1 to the cores (``None``: as set, else the mode's default)
        :raises ValueError: a bad mode or worker count, in one line naming it
        """
        if mode not in MODES:
            raise ValueError(f"lookahead's mode must be one of {list(MODES)}, got {mode!r}")
        self.close()
        self.__dict__.pop("_searcher", None)
        clock = "wall" if mode == "async" else "steps"
        self.search = replace(self.search, mode=mode, clock=clock, workers=workers or self.search.workers)
        self.reset()

    def close(self) -> None:
        """End the processes searching beside this planner (they also end with it)."""
        for part in ("_pool", "_process"):
            worker = self.__dict__.pop(part, None)
            if worker is not None:
                worker.close()
        searcher = self.__dict__.get("_searcher")
        if searcher is not None:
            searcher.close()

    def __getstate__(self) -> dict:
        """A copy holds no process (it starts its own when it first searches)."""
        state = dict(self.__dict__)
        for part in ("_pool", "_process", "_inflight"):
            state.pop(part, None)
        return state

    # ------------------------------------------------------------------ acting
    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles and (scene.layout is None or scene.arc is None):
            raise ValueError("lookahead needs the scene's layout and arcs (scenes built by the simulation have them)")
        self.set_windows(self.windows_for(scene))
        return super().act(scene)

    def windows_for(self, scene: Scene) -> np.ndarray:
        """Each vehicle's advice window for this step, searching where the period says so, and the step
        taken (as :meth:`act` does, without planning the accelerations): the label of an ``"advice"`` policy.

        :param scene: the scene now
        :return: ``(n,)`` windows [m] (glide's own window after a search past its budget)
        """
        if scene.layout is not None and (scene.arc is not None or not scene.num_vehicles):
            if scene.num_vehicles:
                self._stopped = np.union1d(self._stopped, scene.vehicle_id[scene.speed < STOP_SPEED])
            if self.search.mode != "sync":
                self._beside(scene)
            elif scene.num_vehicles and self._steps % self._period_steps(scene) == 0:
                self._apply(self._search(scene), scene.time)
        if self._windows_time is not None and scene.time - self._windows_time > self.search.horizon + 1e-9:
            # Windows older than the horizon: the rollouts that chose them saw nothing of now; glide's own window.
            self._apply(None, None)
            self.expired += 1
        if self._windows_time is not None and scene.num_vehicles:
            age = max(0.0, scene.time - self._windows_time)
            self._age_sum, self._age_max, self._age_steps = (
                self._age_sum + age,
                max(self._age_max, age),
                1 + self._age_steps,
            )
        self._steps += 1
        if self._proposed is not None and scene.num_vehicles:  # vehicles that came since: glide's own window
            return _lookup(*self._proposed, scene.vehicle_id, self.params.window)
        if self._road_windows is None or scene.num_vehicles == 0:
            return np.full(scene.num_vehicles, self.params.window)
        return self._road_windows[_roads(scene.layout)[scene.route]]

    def _period_steps(self, scene: Scene) -> int:
        return max(1, int(round(self.search.period / scene.dt)))

    def _apply(self, result: np.ndarray | tuple[np.ndarray, np.ndarray] | None, searched_at: float | None) -> None:
        """Advise from a search's result from now on (``None``: glide's own window)."""
        self._road_windows, self._proposed = result, None
        if isinstance(result, tuple):  # the proposal won
            self._road_windows, self._proposed = None, result
        self._windows_time = searched_at

    # ------------------------------------------------------------------ beside the steps
    def _beside(self, scene: Scene) -> None:
        """A step of the ``"async"`` mode: apply the answer that is due, start the next search."""
        now = time.perf_counter()
        if self._last_step is not None:  # the wall time between steps (the server's clients step in real time)
            gap = now - self._last_step
            self._step_wall = gap if self._step_wall is None else 0.8 * self._step_wall + 0.2 * gap
        self._last_step = now
        self._land(scene)
        if getattr(self, "_inflight", None) is None and self._steps >= self._next_launch and scene.num_vehicles:
            self._launch(scene)
            self._next_launch = self._steps + self._period_steps(scene)

    def _launch(self, scene: Scene) -> None:
        """Start a search from ``scene`` predicted ``latency`` ahead (on the ``"steps"`` clock: run it now, its
        windows held until then)."""
        ahead = self._latency_steps(scene)
        self._ahead_sum += ahead * scene.dt
        self.started += 1
        inflight = dict(generation=self._generation, layout=scene.layout.name, due=self._steps + ahead, done=False)
        request = (self.memory(), self._road_windows, self._proposed, ahead)
        if self.search.clock == "steps":
            searcher = self._twin()
            searcher.adopt_memory(*request[0])
            before = searcher.counters()
            inflight.update(done=True, answer=searcher.search_ahead(scene, *request[1:]))
            self._add_counters(searcher.counters(), before)
        else:
            if self.__dict__.get("_process") is None:
                self._process = SearchProcess(self._twin(), scene.layout)
            self._process.submit((self._generation, scene, *request))
            inflight["wall"] = time.perf_counter()
        self._inflight = inflight

    def _latency_steps(self, scene: Scene) -> int:
        """Steps from a search's start until its windows apply: ``latency``, or else the period; on the ``"wall"``
        clock with ``latency=None``, at least the wall time the last searches took, in the wall time of a step
        (a search that lands on time needs no excuse), at most the horizon."""
        latency = self.search.period if self.search.latency is None else self.search.latency
        steps = max(1, int(round(latency / scene.dt)))
        if self.search.clock == "wall" and self.search.latency is None and self._search_walls and self._step_wall:
            expected = 1.25 * max(self._search_walls) / self._step_wall
            steps = max(steps, min(int(math.ceil(expected)), int(round(self.search.horizon / scene.dt))))
        return steps

    def _land(self, scene: Scene) -> None:
        """Take the answer of the search in flight if it has come: applied when due and still useful, else dropped."""
        inflight = getattr(self, "_inflight", None)
        if inflight is None:
            return
        if not inflight["done"]:
            try:
                answer = self._process.poll()
            except WorkerLost:  # the step goes on with glide's windows; a fresh process takes the next search
                self._process.close()
                self._process = self._inflight = None
                self.worker_restarts += 1
                self.dropped += 1
                self._apply(None, None)
                return
            if answer is None:
                return
            generation, searched_at, result, counters = answer
            self._add_counters(counters, {})
            self._search_walls = (self._search_walls + [time.perf_counter() - inflight["wall"]])[-3:]
            inflight.update(done=True, answer=(searched_at, result), generation=generation)
        if inflight["generation"] != self._generation or inflight["layout"] != getattr(scene.layout, "name", None):
            self.mismatched += 1
            self._inflight = None
            return
        late = self._steps - inflight["due"]
        if late < 0:
            return  # held until the time it was searched for
        self._inflight = None
        if late > 0:
            self.late += 1
            # Still the newest answer (one search runs at a time): applied while its rollouts still cover the step.
            if late >= int(round(self.search.horizon / scene.dt)):
                self.dropped += 1
                return
        self.applied += 1
        self._apply(inflight["answer"][1], inflight["answer"][0])

    def _twin(self) -> LookaheadPlanner:
        """The synchronous planner that runs this one's searches beside the steps (built once)."""
        twin = self.__dict__.get("_searcher")
        if twin is None:
            params = replace(self.search, mode="sync", clock="steps", workers=self.search.processes)
            twin = self._searcher = LookaheadPlanner(self.name, params, self.params, self.proposer)
            twin.reset()
        return twin

    def memory(self) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """What a search starts from besides the scene: glide's memory (order, commitments, held advice) and the
        ids that have stopped."""
        return (self._ids, self._keys, self._committed_at, self._held), self._stopped

    def adopt_memory(self, memory: tuple[np.ndarray, ...], stopped: np.ndarray) -> None:
        """Plan on from :meth:`memory` of another planner (a search's start)."""
        self._ids, self._keys, self._committed_at, self._held = memory
        self._stopped = stopped

    def counters(self) -> dict[str, float]:
        """The counters a search adds to (the ones :meth:`stats` reports for searches run elsewhere)."""
        return dict(searches=self.searches, fallbacks=self.fallbacks, shrunk=self.shrunk, rollouts=self.rollouts,
                    search_seconds=self.search_seconds, proposals_kept=self.proposals_kept,
                    worker_restarts=self.worker_restarts, rollout_steps=self.rollout_steps,
                    critical_steps=self.critical_steps)  # fmt: skip

    def _add_counters(self, after: dict[str, float], before: dict[str, float]) -> None:
        for key, value in after.items():
            setattr(self, key, getattr(self, key) + value - before.get(key, 0))

    def search_ahead(
        self,
        scene: Scene,
        road_windows: np.ndarray | None,
        proposed: tuple[np.ndarray, np.ndarray] | None,
        steps: int,
    ) -> tuple[float, np.ndarray | tuple[np.ndarray, np.ndarray] | None]:
        """A search from ``scene`` predicted ``steps`` policy steps ahead with the windows in force (this planner's
        memory, set by :meth:`adopt_memory`, moves along the prediction).

        :param scene: the scene now
        :param road_windows: the windows per road in force (``None``: glide's own, or ``proposed``)
        :param proposed: the proposal's ``(ids, windows)`` in force
        :param steps: policy steps ahead
        :return: the predicted scene's time and the search's result (as :meth:`_search`)
        """
        ahead = self.predict(scene, steps, road_windows, proposed)
        self._road_windows = road_windows
        if ahead.num_vehicles == 0:
            return ahead.time, road_windows
        return ahead.time, self._search(ahead)

    def predict(
        self,
        scene: Scene,
        steps: int,
        road_windows: np.ndarray | None,
        proposed: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Scene:
        """The scene ``steps`` policy steps ahead, driven as the real step drives it: glide on the windows in force
        behind a shield, no new vehicle. This planner's memory (glide's, who has stopped) moves along.

        :param scene: the scene now (not modified)
        :param steps: policy steps ahead (the scene's ``dt`` each)
        :param road_windows: ``(roads,)`` windows in force (``None``: glide's own window, or ``proposed``)
        :param proposed: the proposal's ``(ids, windows)`` in force, ids sorted
        """
        if steps <= 0 or scene.num_vehicles == 0:
            return scene
        frequency = int(round(1.0 / scene.dt))
        sim = self._predictor
        stale = sim is None or sim.layout is not scene.layout or sim.policy_frequency != frequency
        if stale or sim.simulation_frequency != _rate(scene, frequency):
            sim = self._predictor = _simulation(scene, frequency)
        _set(sim, scene)
        me = self.fork()
        shield = Shield(me, watchdog_after=None)
        roads = _roads(scene.layout)
        for _ in range(steps):
            if sim.num_vehicles == 0:
                break
            now = sim.rollout_scene()
            if proposed is not None:
                me.set_windows(_lookup(*proposed, now.vehicle_id, self.params.window))
            elif road_windows is not None:
                me.set_windows(road_windows[roads[now.route]])
            sim.step(shield.check_output(now, me.act(now), me.name))
            self._stopped = np.union1d(self._stopped, sim.vehicle_id[sim.speed < STOP_SPEED])
        self.adopt(me)
        return sim.scene()

    def propose(self, scene: Scene) -> np.ndarray:
        """The proposer's advice windows for the vehicles of ``scene`` (as its environment's action sets them).

        :return: ``(n,)`` windows [m], >= 0
        """
        return self.proposer.scheduler.advice_windows(self.proposer.offsets(scene.copy()))

    # ------------------------------------------------------------------ search
    def _search(self, scene: Scene) -> np.ndarray | tuple[np.ndarray, np.ndarray] | None:
        """The cheapest windows per approach road, the proposal's ``(ids, windows)`` where it costs less than
        every one, or ``None`` (glide's own window) past the budget or when a rollout worker was lost. Waves of
        rollouts that would pass the ``step_budget`` are cut (:class:`_StepBudget`)."""
        tic = time.perf_counter()
        self.searches += 1
        n_roads = int(_roads(scene.layout).max()) + 1
        deadline = tic + self.search.budget
        costs: dict[tuple[float, ...], float] = {}
        same = _equivalent_windows(scene, n_roads, self.search.windows)
        budget = _StepBudget(self.search, scene.num_vehicles)

        def key(windows: tuple[float, ...]) -> tuple[float, ...]:
            return tuple(same[r][w] for r, w in enumerate(windows))

        def evaluate(candidates: list[tuple[float, ...]]) -> list[tuple[float, ...]]:
            """Roll out the candidates not yet costed, in order, the first ones that fit the step budget (over the
            workers, if any); return the candidates costed. A cost only grows along a rollout: one past the
            cheapest so far cannot win, so it stops there."""
            todo = budget.take(list({key(w): w for w in candidates if key(w) not in costs}.items()))
            pool = self._rollout_pool(scene) if len(todo) > 1 else None
            if pool is not None:
                if time.perf_counter() > deadline:
                    raise TimeoutError
                costs.update(pool.costs(self, scene, todo, min(costs.values(), default=math.inf)))
            else:
                before = self.rollout_steps
                for k, windows in todo:
                    if time.perf_counter() > deadline:
                        raise TimeoutError
                    costs[k] = self.rollout(scene, np.array(windows), bound=min(costs.values(), default=math.inf))
                self.critical_steps += self.rollout_steps - before
            return [w for w in candidates if key(w) in costs]

        def cost(windows: tuple[float, ...]) -> float:
            return costs[key(windows)]

        try:
            # The windows of the last search first: usually still the cheapest, so the others stop early.
            first = () if self._road_windows is None else (tuple(self._road_windows.tolist()),)
            flat = [(w,) * n_roads for w in self.search.windows]
            order = [w for w in first if w in flat] + [w for w in flat if w not in first]
            distinct = len({key(w) for w in order})
            if distinct > 1 and budget.rounds(distinct) * budget.processes < 2:
                budget.shrunk = True  # not even two candidates fit: the first, without a rollout
                best = order[0]
            else:
                costed = evaluate(order)
                best = min(costed, key=lambda w: (cost(w), flat.index(w)))
            if self.search.per_approach and not budget.shrunk:
                for road in self._road_order(scene, same, budget):
                    tried = [best[:road] + (w,) + best[road + 1 :] for w in self._window_order(road)]
                    costed = evaluate(tried)
                    rank = self.search.windows.index
                    best = min(costed, key=lambda w: (cost(w), w != best, rank(w[road])))
                    if budget.shrunk:
                        break
            if self.proposer is not None and budget.take([((), ())]):
                if time.perf_counter() > deadline:
                    raise TimeoutError
                order = np.argsort(scene.vehicle_id)
                proposed = (scene.vehicle_id[order], self.propose(scene)[order])
                if self.rollout(scene, None, bound=cost(best), proposed=proposed) < cost(best):
                    self.proposals_kept += 1
                    self.search_seconds += time.perf_counter() - tic
                    self.shrunk += budget.shrunk
                    return proposed
        except TimeoutError:
            self.fallbacks += 1
            best = None
        except WorkerLost:  # the search is void: glide's own window until the next one, with fresh workers
            self.fallbacks += 1
            self.worker_restarts += 1
            self._pool.replace_dead(self, scene.layout)
            best = None
        self.shrunk += budget.shrunk
        self.search_seconds += time.perf_counter() - tic
        return None if best is None else np.array(best)

    def _road_order(self, scene: Scene, same: list[dict[float, float]], budget: _StepBudget) -> list[int]:
        """The roads of the greedy pass: all in their order where the whole pass fits the step budget, else the
        roads where the windows differ, the most vehicles before their line first (where a window matters most)."""
        distinct = [len(set(road.values())) - 1 for road in same]
        if budget.fits(distinct):
            return list(range(len(same)))
        roads = _roads(scene.layout)[scene.route]
        before = np.bincount(roads[scene.dist_to_entry > 0], minlength=len(same))
        return sorted((r for r in range(len(same)) if distinct[r]), key=lambda r: -int(before[r]))

    def _window_order(self, road: int) -> tuple[float, ...]:
        """The candidates of one road, the last search's window first (the likeliest best: a tighter bound)."""
        windows = self.search.windows
        if self._road_windows is None or road >= len(self._road_windows):
            return windows
        last = float(self._road_windows[road])
        return tuple(w for w in windows if w == last) + tuple(w for w in windows if w != last)

    def _rollout_pool(self, scene: Scene) -> RolloutPool | None:
        """The helpers that share a search's rollouts (started at the first search; ``None``: one process)."""
        if self.search.processes < 2:
            return None
        pool = self.__dict__.get("_pool")
        if pool is None:
            pool = self._pool = RolloutPool(self, self.search.processes, scene.layout)
        return pool

    def rollout(
        self,
        scene: Scene,
        road_windows: np.ndarray | None,
        bound: float = math.inf,
        proposed: tuple[np.ndarray, np.ndarray] | None = None,
        shared: np.ndarray | None = None,
    ) -> float:
        """The cost of driving ``horizon`` seconds from ``scene`` with these windows per approach road.

        :param scene: the scene now (not modified)
        :param road_windows: ``(roads,)`` advice windows [m], indexed like the layout's approach roads
            (``None`` with ``proposed``)
        :param proposed: instead, a window per vehicle: ``(ids, windows)``, ids sorted (no vehicle comes in a
            rollout, so each keeps its own)
        :param bound: stop as soon as the cost so far exceeds this (it only grows): the cost returned is
            then above ``bound`` but not the whole horizon's
        :param shared: ``(1,)`` the cheapest cost that other processes have finished so far (a bound too, read
            every step)
        :return: seconds lost against the lane limits, plus the prices of new stops and of energy
        """
        self.rollouts += 1
        sim = self._load(scene)
        me = self.fork()
        shield = Shield(me, horizon=self.search.shield_horizon, watchdog_after=None)
        lay = sim.layout
        # No vehicle comes in a rollout: each row keeps its window and its "stopped once" mark, filtered as
        # vehicles leave (cheaper per step than looking the ids up again).
        if proposed is None:
            windows = road_windows[_roads(lay)[sim.route]]
        else:
            windows = _lookup(*proposed, sim.vehicle_id, self.params.window)
        stopped = np.isin(sim.vehicle_id, self._stopped)
        # No window wider than 0 (and no advice held): glide advises no one in the whole rollout, so its
        # proposal is full throttle at every step; planning it (a third of a step) is skipped.
        throttle = not (windows > 0).any() and not (me.hold and np.isin(sim.vehicle_id, me._held).any())
        lost = energy = 0.0
        dt = sim.dt
        limit = None  # the lane limits of the state now, where the cost of the last step computed them
        for _ in range(int(round(self.search.horizon / dt))):
            if sim.num_vehicles == 0:
                break
            self.rollout_steps += 1
            # The lean scene, not copied for glide: glide and the shield never write in a scene (a test checks).
            now = sim.rollout_scene(limit)
            if throttle:
                command = shield.check(now, np.full(now.num_vehicles, now.a_max))
            else:
                me.set_windows(windows)
                command = shield.check_output(now, me.act(now), me.name)
            events = sim.step(command)
            windows, stopped, limit = windows[events.kept], stopped[events.kept], None
            live = sim.arc - sim.length / 2 < lay.exit_arc[sim.route]
            if self.search.energy_price:  # the sub-step speeds of every vehicle of the step
                energy += float(traction_energy(events.speeds[:-1], events.speeds[1:], dt / sim.substeps).sum())
            if not live.any():
                continue
            limit = lay.limit_at(sim.route, sim.arc)
            lost += float(np.clip(1.0 - sim.speed[live] / np.maximum(limit, 1e-3)[live], 0.0, 1.0).sum()) * dt
            new = live & (sim.speed < STOP_SPEED) & ~stopped
            if new.any():
                stopped |= new
                lost += self.search.stop_price * int(new.sum())
            if lost > bound or (shared is not None and lost > shared[0]):
                break
        return lost + self.search.energy_price * energy / 1e3

    def _load(self, scene: Scene) -> Simulation:
        """The simulation of the rollouts, set to ``scene`` (built once per layout and reused)."""
        sim = self._sim
        rate = _rate(scene, self.search.rollout_frequency)
        if sim is None or sim.layout is not scene.layout or sim.simulation_frequency != rate:
            sim = self._sim = _simulation(scene, self.search.rollout_frequency)
        _set(sim, scene)
        return sim


class AsyncLookahead(LookaheadPlanner):
    """``lookahead`` whose search runs beside the steps (``mode="async"``), emulated deterministically in simulated
    time: the planner of ``evaluate`` and ``sweep`` with ``--search-mode async``."""

    def __init__(self) -> None:
        super().__init__("LookaheadAsync", LookaheadParams(mode="async"))


#: The planner spec that ``--search-mode async`` puts in place of the word ``lookahead``.
ASYNC_SPEC = f"{__name__}:AsyncLookahead"


class _StepBudget:
    """The vehicle-steps left to a search's critical path (:class:`LookaheadParams`' ``step_budget``), spent wave by
    wave at each wave's most: its rounds over the processes x the horizon's rollout steps x the vehicles now."""

    def __init__(self, params: LookaheadParams, vehicles: int) -> None:
        self.left = params.step_budget * params.period
        self.processes = params.processes
        self.round = int(round(params.horizon * params.rollout_frequency)) * max(vehicles, 1)
        self.shrunk = False  # a wave was cut

    def rounds(self, candidates: int) -> int:
        """The rounds that ``candidates`` rollouts take over the processes, at most the rounds left."""
        need = math.ceil(candidates / self.processes)
        return need if self.left == math.inf else min(need, int(self.left // self.round))

    def fits(self, waves: list[int]) -> bool:
        """Whether waves of these many rollouts all fit."""
        return sum(math.ceil(n / self.processes) for n in waves) * self.round <= self.left

    def take(self, todo: list) -> list:
        """The first of ``todo`` that fit (its rounds spent); a cut marks the search shrunk."""
        keep = min(len(todo), self.rounds(len(todo)) * self.processes)
        self.shrunk |= keep < len(todo)
        self.left -= math.ceil(keep / self.processes) * self.round
        return todo[:keep]


def _rate(scene: Scene, policy_frequency: int) -> int:
    """The integration rate of the rollouts [Hz]: the plant's (``Scene.substeps``, e.g. SUMO's 20 Hz), so that they
    drive as the real step does, where ``policy_frequency`` divides it; else our plant's default 15 Hz."""
    if scene.substeps is not None:
        rate = int(round(scene.substeps / scene.dt))
        if rate % policy_frequency == 0:
            return rate
    return 15


def _simulation(scene: Scene, policy_frequency: int) -> Simulation:
    """A simulation of the scene's layout to plan ahead in (no collision check: behind the shield it finds nothing)."""
    return _RolloutSimulation(
        scene.layout,
        simulation_frequency=_rate(scene, policy_frequency),
        policy_frequency=policy_frequency,
        max_speed=20.0,
        max_acceleration=float(scene.a_max),
        s_ref=scene.s_ref,
        max_vehicles=max(256, scene.num_vehicles),
        check_collisions=False,
    )


def _set(sim: Simulation, scene: Scene) -> None:
    """Set ``sim`` to the vehicles of ``scene``."""
    width = np.full(scene.num_vehicles, 2.0) if scene.width is None else scene.width
    sim.set_state(scene.time, scene.route, scene.vehicle_id, scene.arc, scene.speed, scene.length, width, scene.humans)


class _RolloutSimulation(Simulation):
    """The rollouts' simulation: its steps integrate with the shield's compiled vehicle model
    (:func:`envs.planners._shield_kernel.integrate`, bit for bit :func:`envs.simulation.engine.integrate`),
    a tenth of a rollout step less than in NumPy."""

    def _integrate(self, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _shield_kernel.integrate(
            envelope_table(self.layout, self.governor_deceleration),
            np.ascontiguousarray(self.route, dtype=np.int64),
            np.ascontiguousarray(self.arc, dtype=float),
            np.ascontiguousarray(self.speed, dtype=float),
            np.ascontiguousarray(acc, dtype=float),
            self.substeps,
            1.0 / self.simulation_frequency,
            self.max_speed,
        )


def _equivalent_windows(scene: Scene, n_roads: int, windows: tuple[float, ...]) -> list[dict[float, float]]:
    """Per approach road, each candidate window mapped to the first candidate that drives its road's vehicles the
    same in every rollout, so that two sets of windows that differ only there share one rollout.

    No vehicle comes in a rollout and a distance to the line never grows, and glide advises a vehicle only while
    ``0 < dist <= window``: on a road with no vehicle before its line every window is the same, and windows at
    least as wide as the farthest vehicle's distance advise all of them from the start. The margin keeps any
    doubt on the side of a rollout of its own.
    """
    margin = 1e-6
    roads = _roads(scene.layout)[scene.route] if scene.num_vehicles else np.zeros(0, np.int64)
    before = scene.dist_to_entry > -margin if scene.num_vehicles else np.zeros(0, bool)
    farthest = np.full(n_roads, -math.inf)
    np.maximum.at(farthest, roads[before], scene.dist_to_entry[before])
    same = []
    for r in range(n_roads):
        if farthest[r] == -math.inf:  # no one to advise: every window drives alike
            same.append(dict.fromkeys(windows, windows[0]))
            continue
        wide = [w for w in windows if w >= farthest[r] + margin]
        same.append({w: (wide[0] if w in wide else w) for w in windows})
    return same


def _lookup(ids: np.ndarray, values: np.ndarray, query: np.ndarray, default: float) -> np.ndarray:
    """``values`` of the ``query`` ids among the sorted ``ids`` (``default`` for an id not there)."""
    if ids.size == 0:
        return np.full(query.shape, default)
    pos = np.minimum(np.searchsorted(ids, query), ids.size - 1)
    return np.where(ids[pos] == query, values[pos], default)


@functools.lru_cache(maxsize=8)
def _roads(layout) -> np.ndarray:
    """``(R,)`` index of each route's approach road (its entry arm ``<arm>-><exit>``)."""
    arms = [name.split("->")[0] for name in layout.route_names]
    return np.unique(arms, return_inverse=True)[1].astype(np.int64)
