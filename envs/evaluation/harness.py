"""Run planners on scenario files, like for like, in parallel processes or on a cluster.

One *job* is one planner on one scenario file: the environment is reset onto the scenario, and
at every policy step the planner answers the scene the environment shows
(``env.unwrapped.scene()``) with one acceleration per vehicle, which the environment turns into
its action (``env.unwrapped.accelerations_to_action``). The step records (``info["record"]``,
:class:`envs.simulation.step_record.StepRecord`) and the scenes go into a vehicle log
(:class:`envs.evaluation.metrics.VehicleLog`), reduced to one metrics row per job, with the counters the planner
reports (:meth:`envs.planners.Planner.stats`: a shield's interventions).

Every planner meets exactly the same traffic: the scenario file fixes every vehicle's appearance
time, route and initial speed, and the environment's own randomness is seeded per scenario.

The harness reads every scenario file once, into a table that goes to each worker once (not once per
run), and hands the jobs to an executor (:mod:`sb3_graph.common.executors`): processes on this machine
(``local``, the default), or an existing Dask or Ray cluster; the results are the same wherever
they ran.

A collision does not end an evaluation run: the harness makes its environments with
``config={"collision_handling": "remove"}`` (unless ``env_kwargs`` sets that key), so the vehicles
involved are counted as collided and leave the scene while the run goes on, and a planner that
crashes is still measured over the whole duration (the paper's collision rate is a share of the
vehicles over full runs).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from envs.evaluation.metrics import VehicleLog, run_metrics
from envs.evaluation.progress import RunClock, format_eta, interleaved
from envs.planners import BASELINES, SHIELD_SUFFIX, make_planner
from envs.planners.errors import PlannerError, checked_accelerations
from envs.planners.shield_bounds import EXCURSION_COLUMNS, ShieldBounds, excursions
from envs.simulation.engine import PlantError
from envs.simulation.rewards import REWARD_PRESETS
from envs.simulation.step_record import StepRecord, step_record
from envs.simulation.traffic import Scenario, demand_scenario, generate_scenario
from sb3_graph.common.executors import JobExecutor, make_executor

SCENARIO_SUFFIX = ".json"


@dataclass(frozen=True)
class Job:
    """One planner on one scenario.

    :param planner: planner word (``"pr"``, ``"fifo"`` or a model path)
    :param name: the planner's report name
    :param scenario: scenario file
    :param index: index of the scenario (seeds the environment: ``seed + index``)
    :param env_id: gymnasium id of the environment
    :param duration: simulated seconds per run
    :param seed: base seed
    :param env_kwargs: keyword arguments of ``gym.make``
    :param trust_files: load a model ``.zip`` with SB3's full ``load`` (``--trust-planner-files``)
    :param shield_bounds: the faults a ``+shield`` planner's shield is declared to tolerate (``None``: the exact world);
        a run's ``fault_excursions`` are counted against them
    """

    planner: str
    name: str
    scenario: str
    index: int
    env_id: str
    duration: float
    seed: int
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    trust_files: bool = False
    shield_bounds: ShieldBounds | None = None


# What the harness's environments do on a collision (see the module docstring).
EVALUATION_CONFIG = {"collision_handling": "remove"}
# Per-worker caches: a worker runs many jobs, so it builds its envs and planners (model loads) once.
# Per thread, since a cluster worker with several threads runs jobs side by side, and an env or a
# planner with state must not serve two runs at once.
_CACHES = threading.local()
_WORKER_READY = False


def _cache(name: str) -> dict:
    """This thread's cache ``name`` (``"envs"`` or ``"planners"``)."""
    if not hasattr(_CACHES, name):
        setattr(_CACHES, name, {})
    return getattr(_CACHES, name)


def _worker_init() -> None:
    """Once per worker process: one torch thread (the jobs are the parallelism)."""
    global _WORKER_READY
    if _WORKER_READY:
        return
    _WORKER_READY = True
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # torch is only needed by learned planners
        pass


def evaluation_env_kwargs(env_kwargs: dict[str, Any] | None) -> dict[str, Any]:
    """``gym.make`` keyword arguments of the harness: the user's, with :data:`EVALUATION_CONFIG`
    merged under their ``config`` (a key the user sets wins).

    :param env_kwargs: the user's keyword arguments (``--env-kwargs``)
    :return: a new dictionary
    :raises ValueError: ``config`` is given but is not a dict
    """
    kwargs = dict(env_kwargs or {})
    config = kwargs.get("config") or {}
    if not isinstance(config, dict):
        raise ValueError(f"env_kwargs: 'config' must be a dict, got {type(config).__name__}")
    kwargs["config"] = {**EVALUATION_CONFIG, **config}
    return kwargs


def _env(env_id: str, env_kwargs: dict[str, Any]):
    import gymnasium as gym

    envs_made = _cache("envs")
    key = (env_id, repr(sorted(env_kwargs.items())))
    if key not in envs_made:
        _check_render_mode(env_id, env_kwargs.get("render_mode"))
        envs_made[key] = gym.make(env_id, **evaluation_env_kwargs(env_kwargs))
    return envs_made[key]


def _check_render_mode(env_id: str, mode: Any) -> None:
    """Refuse a ``render_mode`` that the environment does not offer before ``gym.make`` (which warns, then
    fails inside the environment).

    :raises ValueError: naming ``render_mode`` and the environment's modes
    """
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    if mode is None or env_id not in gym.registry:
        return
    entry_point = gym.registry[env_id].entry_point
    creator = load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
    modes = list(getattr(creator, "metadata", {}).get("render_modes", []))
    if mode not in modes:
        raise ValueError(f"render_mode must be None or one of {modes}, got {mode!r}")


def _planner(spec: str, trust_files: bool = False, shield_bounds: ShieldBounds | None = None):
    planners = _cache("planners")
    key = (spec, trust_files, shield_bounds)
    if key not in planners:
        planners[key] = make_planner(spec, trust_files=trust_files, shield_bounds=shield_bounds)
    return planners[key]


def run_episode(
    env,
    planner,
    scenario: Any,
    duration: float,
    seed: int | None = None,
    on_step: Callable[[Any, np.ndarray, StepRecord, Any], None] | None = None,
    bounds: ShieldBounds | None = None,
) -> tuple[pd.DataFrame, dict]:
    """Run one planner through one scenario.

    :param env: the environment (a gymnasium env whose ``unwrapped`` provides ``scene()`` and
        ``accelerations_to_action(acc)``, and whose ``reset`` and ``step`` put a
        :class:`~envs.simulation.step_record.StepRecord` into ``info["record"]``)
    :param planner: a :class:`envs.planners.Planner`
    :param scenario: the scenario object, passed as ``reset(options={"scenario": scenario})``
    :param duration: simulated seconds to run (less if the environment ends the episode)
    :param seed: seed of the environment's reset and of the planner
    :param on_step: called after every policy step as ``on_step(scene, accelerations, record, next_scene)``
        (e.g. to draw the episode, :mod:`envs.simulation.rendering`); it must not change what it is handed
    :param bounds: the declared bounds that the perceived scenes' excursions are counted against (default: the
        planner's own ``bounds``, a shield's, else the exact world)
    :return: ``(vehicle log, facts)``: the log holds every vehicle scheduled within the run (see
        :mod:`envs.evaluation.metrics`); facts ``return`` (the sum of the environment's rewards),
        ``return_<preset>`` (the same run's return under each reward preset of :mod:`envs.simulation.rewards`),
        ``duration`` (simulated seconds actually run),
        ``steps``, ``terminated`` (the environment ended the episode, e.g. on a collision with
        ``collision_handling="terminate"``; the harness's own environments go on instead), ``lost`` (vehicles the
        plant lost on its own: SUMO refused to insert them or removed them), and with a fault model the vehicle-steps
        whose perceived state was beyond ``bounds`` (:data:`envs.planners.shield_bounds.EXCURSION_COLUMNS`)
    """
    base = env.unwrapped
    _, info = env.reset(seed=seed, options={"scenario": scenario})
    record = step_record(info)
    planner.reset(seed)
    log = VehicleLog(layout=getattr(base, "layout", None))
    log.record(record)
    scene, truth = base.scene(), _true_scene(base)
    start = float(scene.time)
    now = start
    steps = 0
    total = 0.0
    terms: dict[str, float] = {}
    terminated = truncated = False
    lost = 0
    errors = getattr(base, "perception_errors", None)  # None: an environment without a fault model
    if bounds is None:
        bounds = getattr(planner, "bounds", None)
    beyond = np.zeros(len(EXCURSION_COLUMNS), np.int64)
    while now - start < duration - 1e-9 and not (terminated or truncated):
        log.observe(truth)  # the metrics read the truth, the planner what is perceived (the same without faults)
        if errors is not None:  # the vehicle-steps planned on a state beyond the declared bounds
            beyond += excursions(errors(), bounds)
        acc = planned_accelerations(planner, scene)
        _, reward, terminated, truncated, info = env.step(base.accelerations_to_action(acc))
        record = step_record(info)
        log.record(record)
        total += float(reward)
        lost += record.lost.size
        for key, value in record.reward_terms.items():
            terms[key] = terms.get(key, 0.0) + float(value)
        steps += 1
        next_scene, next_truth = base.scene(), _true_scene(base)
        if on_step is not None:
            on_step(truth, acc, record, next_truth)
        scene, truth = next_scene, next_truth
        now = float(record.time)
    log.finish(truth)
    facts = {"duration": now - start, "steps": steps, "terminated": bool(terminated), "return": total, "lost": lost}
    facts.update(preset_returns(terms))
    facts["waiting_at_end"] = int(record.waiting) if steps else 0
    if errors is not None and errors() is not None:
        facts.update(zip(EXCURSION_COLUMNS, beyond.tolist()))
    return log.frame(schedule=_schedule(scenario), end=now), facts


def _true_scene(base) -> Any:
    """The environment's true scene (``true_scene()``, which an environment with a fault model has), else its scene."""
    true_scene = getattr(base, "true_scene", None)
    return base.scene() if true_scene is None else true_scene()


def preset_returns(terms: dict[str, float]) -> dict[str, float]:
    """A run's return under each reward preset, from the sums of its unweighted terms.

    :param terms: ``term -> sum over the run's steps``
    :return: ``{"return_<preset>": value}`` for every preset of :data:`envs.simulation.rewards.REWARD_PRESETS`
    """
    return {
        f"return_{name}": float(sum(weight * terms.get(key, 0.0) for key, weight in weights.items()))
        for name, weights in REWARD_PRESETS.items()
    }


def planned_accelerations(planner, scene) -> np.ndarray:
    """The planner's answer to a private copy of ``scene`` (what it does to the copy stays there),
    checked (:func:`envs.planners.errors.checked_accelerations`).

    :param planner: a :class:`envs.planners.Planner`
    :param scene: the harness's scene, which the metrics read
    :return: ``(n,)`` accelerations within the scene's bounds
    :raises PlannerError: the output is not a valid command, or the planner raised (chained)
    """
    name = getattr(planner, "name", type(planner).__name__)
    try:
        output = planner.act(scene.copy())
    except PlannerError:
        raise
    except Exception as error:  # noqa: BLE001 - whatever a planner raises is the planner's error
        raise PlannerError(name, scene, f"raised {type(error).__name__}: {error}") from error
    return checked_accelerations(output, scene, name)


def _schedule(scenario: Any):
    """The :class:`envs.simulation.traffic.Scenario` behind a ``reset`` option (``None`` for none)."""
    if isinstance(scenario, (str, Path)):
        return Scenario.load(scenario)
    return scenario if isinstance(scenario, Scenario) else None


def run_job(job: Job, scenario: Any = None) -> tuple[dict[str, Any], pd.DataFrame]:
    """Run one job (in whichever process calls it).

    :param job: what to run
    :param scenario: the loaded :class:`envs.simulation.traffic.Scenario` of ``job.scenario`` (default: read the file)
    :return: ``(metrics row, vehicle log)``, both tagged with planner, run and scenario
    """
    tic = time.perf_counter()
    env = _env(job.env_id, job.env_kwargs)
    planner = _planner(job.planner, job.trust_files, job.shield_bounds)
    if scenario is None:
        scenario = Scenario.load(job.scenario)
    row: dict[str, Any] = {"planner": job.name, "run": job.index, "scenario": Path(job.scenario).name}
    try:
        vehicles, facts = run_episode(
            env, planner, scenario, job.duration, seed=run_seed(job.seed, job.index), bounds=job.shield_bounds
        )
    except (PlannerError, PlantError) as error:
        # The run is void; the other runs of the evaluation go on and are reported.
        error.planner = job.name
        row.update(failed=True, planner_error=error.line(Path(job.scenario).name), wall_s=time.perf_counter() - tic)
        return row, pd.DataFrame({"planner": pd.Series(dtype=object), "run": pd.Series(dtype=np.int64)})
    finally:
        plant = getattr(env.unwrapped, "sim", None)
        if plant is not None:  # the cached environment keeps no SUMO open between runs (one per process)
            plant.close()
    duration = facts["duration"] if facts["duration"] > 0 else job.duration
    row.update(run_metrics(vehicles, duration))
    stats = planner.stats()  # the planner's counters of this run (a shield: interventions, unresolved steps ...)
    row.update(stats)
    if "planner_errors" in stats:  # it answers planner errors itself (a shield): the first ones, one line each
        lines = [error.line(Path(job.scenario).name) for error in planner.errors]
        row["planner_error"] = "\n".join(lines) if lines else None
    row.update({key: value for key, value in facts.items() if key.startswith("return") or key in EXCURSION_COLUMNS})
    lost = dict(getattr(getattr(env.unwrapped, "sim", None), "lost", None) or {})
    if lost:  # the plant lost vehicles on its own (SUMO): the run does not measure the scenario; say so, once
        first = next(iter(lost.items()))
        line = PlantError(f"{len(lost)} vehicles lost, the first: id {first[0]}, {first[1]}").line(
            Path(job.scenario).name
        )
        row["planner_error"] = "\n".join(filter(None, [row.get("planner_error"), line]))
    row.update(
        failed=bool(lost),
        baseline=is_baseline(job.planner),
        steps=facts["steps"],
        terminated=facts["terminated"],
        waiting_at_end=facts["waiting_at_end"],
        lost_vehicles=facts["lost"],
        wall_s=time.perf_counter() - tic,
    )
    vehicles.insert(0, "scenario", Path(job.scenario).name)
    vehicles.insert(0, "run", job.index)
    vehicles.insert(0, "planner", job.name)
    return row, vehicles


def run_seed(seed: int, index: int) -> int:
    """The seed of the environment's reset and of the planner in run ``index`` of an evaluation with base ``seed``.

    :param seed: the evaluation's base seed (``--seed``)
    :param index: the scenario's index
    """
    return int(seed) + int(index)


def run_shared_job(job: Job, scenarios: Sequence[Any]) -> tuple[dict[str, Any], pd.DataFrame, bool]:
    """The executors' task: :func:`run_job` with the scenario from the shared table.

    :param job: what to run
    :param scenarios: every scenario of the evaluation, loaded, in the order of ``job.index``
    :return: :func:`run_job`'s result and whether the run was warm (its worker had built its planner before:
        its wall time is a sample of the planner's speed, see :class:`envs.evaluation.progress.RunClock`)
    """
    _worker_init()
    warm = (job.planner, job.trust_files, job.shield_bounds) in _cache("planners")
    return (*run_job(job, scenarios[job.index]), warm)


def is_baseline(spec: str) -> bool:
    """Whether a planner spec is a built-in (non-learned) planner word rather than a model file,
    with or without the shield (full throttle behind the shield is the strongest baseline)."""
    key = str(spec).strip().lower()
    return key.removesuffix(SHIELD_SUFFIX) in BASELINES


def generate_scenarios(
    folder: str | Path,
    count: int,
    duration: float,
    seed: int,
    layout: str,
    demand: float | None = None,
    human_share: float = 0.0,
) -> list[Path]:
    """Generate ``count`` scenario files ``scenario_000.json``... into ``folder``.

    Scenario ``i`` is drawn with seed ``seed + i``, so the same arguments give the same files.

    :param folder: where to write them (created)
    :param count: number of scenarios
    :param duration: seconds of traffic in each
    :param seed: base seed
    :param layout: name of the intersection layout (see :func:`layout_of`)
    :param demand: arrival rate per major-road lane [veh/s] (minor lanes get half); default: a
        rate drawn per scenario from the paper's range (:func:`envs.simulation.traffic.generate_scenario`)
    :param human_share: probability that a vehicle is human-driven (mixed traffic); it only
        adds flags, so the arrivals of scenario ``i`` are the same at every share
    :return: the files, in order
    """
    if count < 1:
        raise ValueError(f"count (--scenarios) must be at least 1, got {count}")
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    width = max(3, len(str(count - 1)))
    paths = []
    for i in range(count):
        path = folder / f"scenario_{i:0{width}d}{SCENARIO_SUFFIX}"
        if path.exists():
            raise FileExistsError(f"{path} exists: scenario files are never overwritten")
        if demand is None:
            generate_scenario(layout, duration, seed + i, human_share=human_share).save(path)
        else:
            demand_scenario(layout, duration, seed + i, demand, human_share=human_share).save(path)
        paths.append(path)
    return paths


def layout_of(env_id: str, env_kwargs: dict[str, Any] | None = None) -> str:
    """The layout name an environment uses (what its scenarios must be drawn for).

    :param env_id: gymnasium id
    :param env_kwargs: keyword arguments of ``gym.make``
    :return: e.g. ``"4way"``
    """
    return str(env_config(env_id, env_kwargs)["layout"])


def env_config(env_id: str, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The resolved configuration of the harness's environment (``max_vehicles``, ``layout`` ...).

    :param env_id: gymnasium id
    :param env_kwargs: keyword arguments of ``gym.make``
    :return: a copy of ``env.unwrapped.config``
    """
    return dict(_env(env_id, dict(env_kwargs or {})).unwrapped.config)


def find_scenarios(folder: str | Path) -> list[Path]:
    """The scenario files of a folder, sorted by name.

    :param folder: folder written by :func:`generate_scenarios` (or by hand)
    :return: the files
    :raises ValueError: the folder does not exist or holds no scenario file
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"scenario folder {str(folder)!r} does not exist")
    paths = sorted(folder.glob(f"*{SCENARIO_SUFFIX}"))
    if not paths:
        raise ValueError(f"scenario folder {str(folder)!r} holds no *{SCENARIO_SUFFIX} scenario file")
    return paths


def check_scenarios(paths: Sequence[str | Path], layout: str) -> None:
    """Read every scenario file and check that it is for ``layout``.

    :param paths: scenario files
    :param layout: the environment's layout name
    :raises ValueError: an unreadable or invalid file, or one for another layout (naming the file)
    """
    for path in paths:
        scenario = Scenario.load(path)
        if scenario.layout != layout:
            raise ValueError(
                f"{path}: scenario is for layout {scenario.layout!r}, the environment uses {layout!r}"
            )


def evaluate(
    planners: Sequence[tuple[str, str]],
    scenarios: Sequence[str | Path],
    env_id: str,
    duration: float,
    seed: int = 0,
    jobs: int = 1,
    env_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
    trust_planner_files: bool = False,
    executor: str | JobExecutor = "local",
    scheduler_address: str | None = None,
    stats: dict[str, Any] | None = None,
    progress_label: str = "evaluate",
    shield_bounds: ShieldBounds | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Run every planner on every scenario.

    :param planners: ``(word, report name)`` pairs, e.g. ``[("pr", "PR"), ("fifo", "FIFO")]``
    :param scenarios: scenario files (each is read once, here, and shared with the workers)
    :param env_id: gymnasium id of the environment
    :param duration: simulated seconds per run
    :param seed: base seed (scenario ``i`` runs with ``seed + i``)
    :param jobs: parallel workers (``local``: processes, 1 runs in this process; ``dask``/``ray``
        without ``scheduler_address``: the workers of the local cluster started for the evaluation)
    :param env_kwargs: keyword arguments of ``gym.make``
    :param progress: show a progress bar (with the runs per second)
    :param trust_planner_files: load model ``.zip`` files with SB3's full ``load`` (runs their pickles)
    :param executor: where the runs execute: ``"local"``, ``"dask"``, ``"ray"``
        (:mod:`sb3_graph.common.executors`), or a :class:`sb3_graph.common.executors.JobExecutor` of one's own, which is
        used as it is and not closed here
    :param scheduler_address: address of an existing Dask scheduler or Ray cluster
    :param stats: if given, filled with the harness's facts: ``runs``, ``wall_s`` (from the start of
        the executor, a cluster started for the evaluation included, to the last result),
        ``runs_per_s`` and ``executor`` (its description)
    :param progress_label: the progress bar's label (the command that runs the harness)
    :param shield_bounds: the faults every ``+shield`` planner's shield is declared to tolerate (``--shield-bounds``;
        ``None``: the exact world); each run's ``fault_excursions`` are counted against them
    :return: ``(runs, vehicles)``: one row per planner and run, one row per vehicle and run;
        sorted by planner (given order) and scenario, whatever order the workers finished in
    """
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    work = [
        Job(word, name, str(path), i, env_id, float(duration), int(seed), dict(env_kwargs or {}),
            trust_planner_files, shield_bounds)  # fmt: skip
        for word, name in planners
        for i, path in enumerate(scenarios)
    ]
    table = [Scenario.load(path) for path in scenarios]
    results: list[tuple[dict[str, Any], pd.DataFrame] | None] = [None] * len(work)
    own = not isinstance(executor, JobExecutor)
    tic = time.perf_counter()  # a cluster started for this evaluation counts in its wall time
    runner = make_executor(executor, jobs, scheduler_address) if own else executor
    bar = _progress(len(work), progress, progress_label)
    # Hand the runs out scenario by scenario (every planner in turn) and price the time left per planner from
    # warm runs (envs.evaluation.progress): the results keep the planner-major order of `work`.
    order = interleaved(len(planners), len(scenarios))
    seconds = [min(job.duration, getattr(table[job.index], "duration", job.duration)) for job in work]
    clock = RunClock([job.planner for job in work], seconds, jobs)
    try:
        for k, result in runner.map_unordered(run_shared_job, [work[i] for i in order], table):
            results[order[k]] = result
            clock.record(order[k], result[0].get("wall_s"), warm=bool(result[2]) if len(result) > 2 else True)
            bar.eta_text = format_eta(clock.remaining_s())
            bar.update(1)
        wall = time.perf_counter() - tic
        if stats is not None:
            stats.update(
                runs=len(work), wall_s=wall, runs_per_s=len(work) / wall if wall > 0 else None,
                executor=runner.describe(),
            )  # fmt: skip
    finally:
        bar.close()
        if own:
            runner.close()
    runs = pd.DataFrame([r[0] for r in results if r is not None])
    vehicles = pd.concat([r[1] for r in results if r is not None], ignore_index=True)
    return runs, vehicles


def _progress(total: int, enabled: bool, label: str = "evaluate"):
    """The harness's bar: runs done, and the time left that :class:`envs.evaluation.progress.RunClock` gives."""
    from tqdm.auto import tqdm

    class _Bar(tqdm):
        eta_text = "?"  # set before each update

        @property
        def format_dict(self):
            return {**super().format_dict, "eta": self.eta_text}

    return _Bar(
        total=total,
        desc=label,
        unit="run",
        # runs per second even below 1 (tqdm's default turns a slow rate into seconds per run)
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{eta}, {rate_noinv_fmt}]",
        disable=not enabled or bool(os.environ.get("SB3_GRAPH_NO_PROGRESS")),
    )
