"""The intersection domain's pieces for ``sb3-graph tune``: the reduced preset and the evaluator.

**The "tuning" preset** (:data:`TUNING_PRESET`, :func:`tuning_env_kwargs`). The paper chose its
reward weights by a grid search "on a reduced variant of the simulation environment resembling the
key behavior, while being much less computationally demanding". This preset is that variant:

=====================  ====  ======  ======================================================
setting                full  tuning  why
=====================  ====  ======  ======================================================
``duration`` [s]       60    20      3x more episodes (resets, fresh traffic) per step budget
``max_vehicles``       64    16      4x smaller graphs, padded arrays and replay batches; a
                                     busy 4-way holds 8 vehicles on average (at most 15 seen)
``max_edges``          1024  192     edges seen in such scenes: median 21, at most 105
=====================  ====  ======  ======================================================

Kept unchanged, because they are the key interactions the weights trade off: the layout (major
and minor roads, same-lane following and crossing conflicts, priorities), the traffic density
(spawn probability, and the experiment entry's curriculum, which each trial runs over its own
shorter budget), vehicle dynamics and limits, the observation features, the reward terms and the
collision ending of an episode.
The environment id and layout come from the study (``--env``), so the preset applies to every
``CoopIntersection*`` id.

**The evaluator** (:func:`evaluate_model`): the trained model behind a
:class:`~envs.planners.gnn.GNNPlanner` face, as the evaluation harness runs the planner that the
training config describes (:func:`trial_planner`): a ``residual_base`` config makes it a
:class:`~envs.planners.residual.ResidualPlanner` on that base with the config's ``residual_scale``,
a ``shield: true`` config puts it behind the safety :class:`~envs.planners.shield.Shield` (as
``sb3-graph evaluate --planner FILE+shield``). It runs :func:`envs.evaluation.harness.run_episode` on a
few validation scenarios, drawn in memory with :func:`envs.simulation.traffic.generate_scenario` exactly
like the evaluation scenarios (the same seeds for every trial), in the harness's environment
(the study's config without ``shield`` and ``residual_base``, which the planner applies, and with
the harness's ``collision_handling``), and :func:`envs.evaluation.metrics.summarize` turns the vehicle logs
into the task metrics: flow rate, collision rate, stop ratio, delay. The training reward is not used.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd

from envs.evaluation.harness import EVALUATION_CONFIG, run_episode
from envs.evaluation.metrics import run_metrics, summarize
from envs.planners import make_residual_base
from envs.planners.base import Planner
from envs.planners.gnn import GNNPlanner
from envs.planners.residual import ResidualPlanner
from envs.planners.shield import Shield
from envs.simulation.traffic import Scenario, generate_scenario

PRESET_NAME = "tuning"
TUNING_PRESET: dict[str, Any] = {"duration": 20.0, "max_vehicles": 16, "max_edges": 192}
# Validation scenarios: long enough for vehicles spawned at the start to cross (about 10-15 s).
EVAL_DURATION_S = 40.0


def tuning_env_kwargs() -> dict[str, Any]:
    """``gym.make`` keyword arguments of the "tuning" preset: ``{"config": TUNING_PRESET}``."""
    return {"config": dict(TUNING_PRESET)}


class ModelPlanner(GNNPlanner):
    """A :class:`GNNPlanner` around a model in memory (a trial's model, not yet saved).

    :param model: the SB3 model (its ``observation_space`` is the env's ``GraphSpace``)
    :param name: report name
    :param vertex_features: the training config's ``vertex_features`` (the observation's optional names)
    :param edge_features: the training config's ``edge_features``
    """

    def __init__(
        self,
        model: Any,
        name: str = "RL:trial",
        vertex_features: Sequence[str] = (),
        edge_features: Sequence[str] = (),
    ) -> None:
        Planner.__init__(self, name)
        self.path = None
        self.model = model
        self.space = model.observation_space
        self.vertex_features, self.edge_features = tuple(vertex_features), tuple(edge_features)
        self._check_features("the trial's model")


def trial_planner(model: Any, config: dict[str, Any]) -> Planner:
    """The planner that a trial's model is under the training config ``config``: the model's command,
    corrected onto ``residual_base`` (scaled by ``residual_scale``) when the config has one, behind the
    :class:`~envs.planners.shield.Shield` when ``shield`` is true (with the config's vehicle-model
    constants, as the training environment's shield).

    :param model: the trial's SB3 model
    :param config: the training environment's config (``env.unwrapped.config``)
    """
    planner: Planner = ModelPlanner(
        model, vertex_features=config.get("vertex_features", ()), edge_features=config.get("edge_features", ())
    )
    base = make_residual_base(config.get("residual_base"))
    if base is not None:
        planner = ResidualPlanner(base, planner, float(config["residual_scale"]), name=planner.name)
    if config.get("shield"):
        planner = Shield(
            planner,
            simulation_frequency=config["simulation_frequency"],
            max_speed=config["max_speed"],
            governor_deceleration=config["governor_deceleration"],
        )
    return planner


def harness_env_kwargs(env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """The validation environment's ``gym.make`` kwargs: the study's, without the training-side
    ``shield`` and ``residual_base`` (the planner of :func:`trial_planner` applies them) and with the
    evaluation harness's collision handling (:data:`envs.evaluation.harness.EVALUATION_CONFIG`)."""
    kwargs = dict(env_kwargs or {})
    config = dict(kwargs.get("config") or {})
    config.update(shield=False, residual_base=None, **EVALUATION_CONFIG)
    kwargs["config"] = config
    return kwargs


@functools.lru_cache(maxsize=8)
def validation_scenarios(layout: str, count: int, duration: float, seed: int) -> tuple[Scenario, ...]:
    """The validation scenarios of a study (drawn once per process; scenario ``i`` uses ``seed + i``).

    :param layout: layout name
    :param count: number of scenarios
    :param duration: seconds of traffic in each
    :param seed: base seed
    """
    return tuple(generate_scenario(layout, duration, seed + i) for i in range(count))


def evaluate_model(
    model: Any,
    env_id: str,
    env_kwargs: dict[str, Any],
    episodes: int = 3,
    seed: int = 10_000,
    duration: float = EVAL_DURATION_S,
) -> dict[str, float]:
    """Task metrics of a trained model, as the planner of its training config (:func:`trial_planner`:
    residual, shielded), on ``episodes`` validation scenarios.

    :param model: trained SB3 model with a graph observation space
    :param env_id: gymnasium id of a ``CoopIntersection*`` environment
    :param env_kwargs: ``gym.make`` keyword arguments (the study's, weights included: they do not
        change the metrics; ``shield`` and ``residual_base`` choose the planner)
    :param episodes: number of validation scenarios, at least 1
    :param seed: base seed of the scenarios and of the environment resets
    :param duration: simulated seconds per scenario
    :return: ``flow_rate`` (mean over scenarios, veh/s), ``flow_rate_median``, ``collision_rate`` and
        ``stop_ratio`` (pooled over all vehicles), ``stop_ratio_major``, ``stop_ratio_minor``,
        ``delay_mean`` [s] (NaN when undefined), ``vehicles``, ``terminated`` (episodes ended by a
        collision: none under the harness's collision handling), and behind the shield
        ``shield_intervention_rate`` (share of vehicle-steps whose command the shield replaced)
    """
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    env = gym.make(env_id, **env_kwargs)
    config = dict(env.unwrapped.config)
    env.close()
    return evaluate_planner(trial_planner(model, config), env_id, env_kwargs, episodes, seed, duration)


def evaluate_planner(
    planner: Planner,
    env_id: str,
    env_kwargs: dict[str, Any],
    episodes: int = 3,
    seed: int = 10_000,
    duration: float = EVAL_DURATION_S,
) -> dict[str, float]:
    """:func:`evaluate_model`'s metrics of any planner on the same validation scenarios.

    :param planner: the planner (a :class:`~envs.planners.shield.Shield` adds ``shield_intervention_rate``)
    :param env_id: gymnasium id of a ``CoopIntersection*`` environment
    :param env_kwargs: the study's ``gym.make`` keyword arguments (see :func:`harness_env_kwargs`)
    :param episodes: number of validation scenarios, at least 1
    :param seed: base seed of the scenarios and of the environment resets
    :param duration: simulated seconds per scenario
    """
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    env = gym.make(env_id, **harness_env_kwargs(env_kwargs))
    interventions = vehicle_steps = 0
    try:
        layout = str(env.unwrapped.config["layout"])
        rows, logs = [], []
        for i, scenario in enumerate(validation_scenarios(layout, int(episodes), float(duration), int(seed))):
            vehicles, facts = run_episode(env, planner, scenario, duration, seed=seed + i)
            interventions += int(getattr(planner, "interventions", 0))  # counted per episode (reset)
            vehicle_steps += int(getattr(planner, "vehicle_steps", 0))
            run_duration = facts["duration"] if facts["duration"] > 0 else duration
            rows.append({"planner": planner.name, **run_metrics(vehicles, run_duration), **facts})
            vehicles.insert(0, "planner", planner.name)
            logs.append(vehicles)
    finally:
        env.close()
    runs = pd.DataFrame(rows)
    summary = summarize(runs, pd.concat(logs, ignore_index=True))[planner.name]

    def number(value: Any) -> float:
        return float("nan") if value is None else float(value)

    metrics = {
        "flow_rate": number(summary["flow_rate"]["mean"]),
        "flow_rate_median": number(summary["flow_rate"]["median"]),
        "collision_rate": number(summary["collision_rate"]),
        "stop_ratio": number(summary["stop_ratio"]["all"]),
        "stop_ratio_major": number(summary["stop_ratio"]["major"]),
        "stop_ratio_minor": number(summary["stop_ratio"]["minor"]),
        "delay_mean": number(summary["delay_s"]["mean"]),
        "vehicles": int(summary["vehicles"]),
        "terminated": int(np.sum(runs["terminated"])),
    }
    if hasattr(planner, "interventions"):
        metrics["shield_intervention_rate"] = interventions / vehicle_steps if vehicle_steps else float("nan")
    return metrics
