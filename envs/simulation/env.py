"""The cooperative intersection environment: one planner commands every vehicle in the scene.

A fast variant of highway-env's intersection (paper, section "Experiments"). It subclasses
highway-env's :class:`~highway_env.envs.common.abstract.AbstractEnv` for its configuration habit
(``default_config()`` merged with the user's dict) and its viewer, but overrides ``reset`` and
``step`` entirely: the state lives in :class:`~envs.simulation.engine.Simulation` arrays, and highway-env
``Vehicle`` objects are made only to render.

- Observation: :class:`sb3_graph.GraphSpace` (``max_vehicles`` vertices, 3 features ``[s, v, d]``,
  ``max_edges`` edges, 2 relations: 0 same lane, 1 crossing), built by
  :func:`envs.simulation.graph.build_observation` from :meth:`CoopIntersectionEnv.scene`.
- Action: ``Box(-1, 1, (max_vehicles,))``; slot ``i`` commands vehicle ``i`` (vertex ``i``) with
  ``action * max_acceleration`` m/s^2; slots beyond the vehicles present are ignored.
- Reward: :mod:`envs.simulation.rewards`; the episode is truncated after ``duration`` seconds (or the
  replayed scenario's duration).
- Collisions (``collision_handling``): ``"terminate"`` (default, training, as in the paper) ends
  the episode (``terminated``) with the vehicles where they collided; ``"remove"`` (evaluation:
  :mod:`envs.evaluation.harness` uses it) reports the pair once in ``info["collisions"]`` and
  ``info["collided"]``, takes both vehicles out of the scene at the end of the step (their ids are
  also in ``info["removed"]``) and goes on, so a run's flow and collision rate cover its whole
  duration. The collision reward term applies in both cases.
- ``info``: the step's :class:`~envs.simulation.step_record.StepRecord` under ``"record"`` (what the metrics and
  the evaluation harness read), and its fields under the keys documented in :mod:`envs.simulation.step_record`.

Traffic: random training spawns with ``spawn_probability`` per lane and step (see
:meth:`CoopIntersectionEnv.set_spawn_probability` for a curriculum), or an exact replay of an
evaluation scenario with ``reset(options={"scenario": scenario_or_path})``.

Public helpers on ``env.unwrapped``: :meth:`~CoopIntersectionEnv.scene` (the current
:class:`~envs.simulation.scene.Scene`), :meth:`~CoopIntersectionEnv.accelerations_to_action` (a planner's
accelerations in m/s^2 -> padded action), :meth:`~CoopIntersectionEnv.set_spawn_probability`,
:meth:`~CoopIntersectionEnv.place_vehicles` (hand-built situations), and the attributes
``layout`` (:class:`~envs.simulation.layouts.Layout`) and ``sim`` (:class:`~envs.simulation.engine.Simulation`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.road import Road
from highway_env.vehicle.graphics import VehicleGraphics
from highway_env.vehicle.kinematics import Vehicle

from envs.simulation import hooks
from envs.simulation.config import SCHEDULER_ACTION_TYPES, validate_config
from envs.simulation.engine import StepEvents
from envs.simulation.faults import FAULT_DEFAULTS
from envs.simulation.graph import DEFAULT_S_SCALE, NUM_RELATIONS, build_observation, min_mahalanobis, num_node_features
from envs.simulation.layouts import Layout
from envs.simulation.perception import Perception
from envs.simulation.plant import Plant, make_plant
from envs.simulation.rewards import (
    DEFAULT_PROXIMITY_THRESHOLD,
    DEFAULT_REWARD,
    DEFAULT_REWARD_WEIGHTS,
    REWARD_TERMS,
    reward_terms,
    task_reward_terms,
    weighted,
)
from envs.simulation.scene import MAJOR, MANEUVERS, Scene
from envs.simulation.step_record import StepRecord
from envs.simulation.sumo_junction import named_layout
from envs.simulation.traffic import Scenario, ScenarioTraffic, TrainingTraffic, human_flags, human_rng
from sb3_graph.callbacks import VERTEX_ORIGIN
from sb3_graph.common.spaces import GraphSpace

_EMPTY_IDS = np.zeros(0, np.int64)


class CoopIntersectionEnv(AbstractEnv):
    """Centralized planning of all vehicles at an intersection (see the module docstring).

    :param config: settings merged into :meth:`default_config` (validated; see :mod:`envs.simulation.config`)
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"``
    """

    LAYOUT = "4way"
    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 5}

    def __init__(self, config: dict | None = None, render_mode: str | None = None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.metadata = dict(self.metadata)  # highway-env writes render_fps into it
        self.sim: Plant | None = None
        self.layout: Layout | None = None
        self.traffic: TrainingTraffic | ScenarioTraffic | None = None
        self._scene: Scene | None = None
        self._truth: Scene | None = None  # what the rewards and metrics read; _scene: what planners perceive
        self._perception: Perception | None = None  # None: no faults, the perceived scene is the truth
        self._duration = 0.0
        self._collided: set[int] = set()
        self._human_rng: np.random.Generator | None = None
        self._human_model = None
        super().__init__(config, render_mode)
        # highway-env's constructor resets once: a plant that holds a simulator (SUMO: one per process) lets it
        # go until the user's own reset, so that building an environment (to read its config) holds nothing.
        self.sim.close()

    @classmethod
    def default_config(cls) -> dict:
        """All settings with their defaults.

        - ``layout``: ``"4way"``, ``"3way"`` or ``"inD"`` (see :func:`envs.simulation.layouts.build_layout`), or
          ``"net:FILE"``: the one junction of a SUMO network (:func:`envs.simulation.sumo_junction.read_junction`)
        - ``plant``: what moves the vehicles (:mod:`envs.simulation.plant`): ``"builtin"`` (our simulation, the
          default) or ``"sumo"`` (Eclipse SUMO, the ``sumo`` extra; ``simulation_frequency`` must then divide
          1000, e.g. 20; human-driven vehicles are SUMO's own drivers)
        - ``simulation_frequency`` [Hz] 15, ``policy_frequency`` [Hz] 5 (a 0.2 s step)
        - ``duration`` [s]: training episode length (a scenario brings its own)
        - ``max_vehicles``: vertices/action slots; spawning waits while the scene is full
        - ``max_edges``: edge slots of the observation
        - ``edge_features``: edge features of the observation, any of ``["distance", "bearing",
          "zone_receiver", "zone_sender"]`` (default none; see :mod:`envs.simulation.graph`)
        - ``vertex_features``: vertex features after the paper's ``[s, v, d]``, any of
          ``["maneuver", "priority", "limit", "line", "zone", "committed", "human"]`` (default none: the paper's)
        - ``spawn_probability``: training spawn probability per lane and step (paper: up to 0.05)
        - ``spawn_probability_range``: ``None``, or ``[low, high]``: each training episode draws its
          spawn probability uniformly from it (one planner for light and heavy traffic); it
          replaces ``spawn_probability`` at every reset (use it without a curriculum)
        - ``initial_spawn_probability``: the same, for the spawn at reset (so episodes start busy)
        - ``initial_speed_range``: initial speed as fractions of the lane limit (paper: 0.6-1.0)
        - ``max_acceleration`` [m/s^2]: commands lie in ``[-max, max]`` (paper: 5)
        - ``max_speed`` [m/s]: speed cap above every lane limit
        - ``lateral_acceleration`` [m/s^2]: largest lateral acceleration on curved lanes; sets their
          speed limits ``sqrt(a_lat / kappa)`` (the road's 10 m/s on straight lanes)
        - ``governor_deceleration`` [m/s^2]: the speed governor, applied after any planner, slows a
          vehicle down at this rate for a lower limit ahead, so that no vehicle exceeds its lane limit
        - ``collision_resolution`` [m]: largest distance a body moves between two collision checks
        - ``vehicle_length``, ``vehicle_width`` [m]: training vehicles
        - ``spawn_min_gap`` [m]: bumper gap required at the spawn point (plus braking distance)
        - ``s_ref`` [m]: common path length inside the intersection; ``s_scale``: factor on ``s``
          (default 0.04: units of 25 m)
        - ``d_max``: clip of the inverse Mahalanobis distance feature
        - ``proximity_threshold``: Mahalanobis distance where the proximity penalty starts
        - ``reward``: the reward preset, ``"task"`` (default: throughput, delay of every scheduled
          vehicle, new stops, collisions, shield overrides) or ``"paper"`` (Table I); see :mod:`envs.simulation.rewards`
        - ``reward_weights``: weights of the reward terms (default: the preset's); the given ones
          replace the preset's
        - ``shield``: train behind the safety shield (:class:`envs.planners.shield.Shield`): the
          policy's proposal is checked as in evaluation, the executed command is applied, rewarded
          and reported in ``info["executed_action"]`` (the graph algorithms store it in the replay
          buffer: the policy's action where the shield kept the proposal, the action of the shield's
          command where it overrode it), and the override enters the ``shield`` reward term
        - ``spawn_queue``: training spawns that find their spawn point blocked wait, up to this many
          per lane (0: dropped); waiting vehicles count in the delay term
        - ``residual_base``: ``None``, or a planner (``"fullthrottle"``, ``"glide"``, ``"aim"``, ``"fifo"``,
          ``"pr"``) whose command the action corrects: ``a = base + residual_scale * action * max_acceleration``
          (a zero action reproduces the base planner)
        - ``residual_scale``: largest correction as a fraction of ``max_acceleration``
        - ``action``: what an action means, highway-env's ``{"type": ...}``: ``"acceleration"``
          (the default: one acceleration per vehicle, as above) or ``"priority"``: one score per
          vehicle in ``[-1, 1]`` that shifts the vehicle's arrival key in the order of glide's
          scheduler (:class:`envs.planners.glide.GlidePlanner`) by ``scale`` seconds per unit
          (default 5; lower goes earlier); the scheduler turns the order into approach profiles and
          accelerations, behind the shield with ``shield``; or ``"advice"``: one score per vehicle in
          ``[-1, 1]`` that moves the distance from its line within which glide advises the vehicle
          (its ``window``) by ``scale`` metres per unit (default 64: +1 is the 4-way's whole
          approach; never below 0 m, where the vehicle drives at full throttle behind the shield).
          ``glide`` names the scheduler's parameters (``"first_phase"``, the default, as ``glide+shield``
          runs; ``"guarded"``, glide as first shipped, :data:`envs.planners.glide.GUARDED`).
          With either type, a zero action drives exactly as that glide does behind the shield in an
          evaluation (``glide+shield`` for the default). Needs ``residual_base`` null.
        - ``collision_handling``: ``"terminate"`` (a collision ends the episode) or ``"remove"``
          (the vehicles involved leave the scene and the episode goes on)
        - ``human_share``: mixed traffic: each training spawn is human-driven with this
          probability, or ``[low, high]`` to draw it per episode (default 0: none, no draw); a
          replayed scenario brings its own flags. Human drivers follow the static priority rules
          (:class:`envs.planners.human.HumanDriver`) inside :meth:`step`: the action (and the
          shield's command) for their slots is ignored; ``Scene.human`` and the vertex feature
          ``"human"`` mark them
        - ``faults``: the fault model of an imperfect world (:mod:`envs.simulation.faults`), a dict of which any
          entries may be given: ``position_sigma`` [m] (0), ``position_bound`` [m] (null: none) and ``position_tau``
          [s] (1): each vehicle's position along its path off by a Gauss-Markov error, clipped at the bound;
          ``speed_sigma``, ``speed_bound``, ``speed_tau`` (0): the same for its speed; ``loss`` (0): probability
          that a vehicle's message of a step is lost (its last state is held, never longer than ``max_age`` [s], 1);
          ``latency`` [s] (0, at most one policy period): the scene is this old, and commands apply this much later;
          ``lag`` [s] (0): first-order lag of the realised acceleration behind the command; ``tracker`` (true):
          the planners see a Kalman tracker's estimate (false: the raw held measurements), ``process_noise``
          [m/s^2] (1): its acceleration noise. The planners, the shield and the observation read the perceived
          scene (``env.unwrapped.scene()``, with ``arc_std``, ``speed_std``, ``age``, ``acceleration``); the rewards,
          the metrics and the collision checks read the truth (``true_scene()``). Every draw comes from the reset's
          seed, per vehicle id and step. With no fault the two scenes are the same arrays
        - rendering: ``screen_width``, ``screen_height``, ``scaling``, ``centering_position``,
          ``offscreen_rendering``, ``real_time_rendering``, ``render_agent``, ``show_trajectories``
        """
        return {
            "layout": cls.LAYOUT,
            "plant": "builtin",
            "simulation_frequency": 15,
            "policy_frequency": 5,
            "duration": 60.0,
            "max_vehicles": 64,
            "max_edges": 1024,
            "edge_features": [],
            "vertex_features": [],
            "spawn_probability": 0.05,
            "spawn_probability_range": None,
            "initial_spawn_probability": 1.0,
            "initial_speed_range": [0.6, 1.0],
            "max_acceleration": 5.0,
            "max_speed": 20.0,
            "lateral_acceleration": 3.0,
            "governor_deceleration": 3.0,
            "collision_resolution": 0.1,
            "vehicle_length": 5.0,
            "vehicle_width": 2.0,
            "spawn_min_gap": 5.0,
            "s_ref": 25.0,
            "s_scale": DEFAULT_S_SCALE,
            "d_max": 10.0,
            "proximity_threshold": DEFAULT_PROXIMITY_THRESHOLD,
            "reward": DEFAULT_REWARD,
            "reward_weights": dict(DEFAULT_REWARD_WEIGHTS),
            "shield": False,
            "spawn_queue": 10,
            "residual_base": None,
            "residual_scale": 0.5,
            "action": {"type": "acceleration"},
            "collision_handling": "terminate",
            "human_share": 0.0,
            "faults": dict(FAULT_DEFAULTS),
            "screen_width": 600,
            "screen_height": 600,
            "scaling": 3.0,
            "centering_position": [0.5, 0.5],
            "offscreen_rendering": None,
            "real_time_rendering": False,
            "render_agent": True,
            "show_trajectories": False,
        }

    def configure(self, config: dict | None) -> None:
        """Merge and validate settings; they take effect at the next ``reset``.

        :param config: settings to change
        :raises ValueError: naming the key and what is allowed
        """
        if config is not None and not isinstance(config, Mapping):  # dict() would take a list of pairs, or fail
            raise ValueError(f"config must be a dict of config keys and values, got {type(config).__name__}")
        self.config = validate_config(dict(config or {}), self.config)
        if self.config["offscreen_rendering"] is None:
            self.config["offscreen_rendering"] = self.render_mode != "human"

    def define_spaces(self) -> None:
        """Graph observation space and one action slot per possible vehicle."""
        self.observation_type = None
        self.action_type = None
        self.observation_space = GraphSpace(
            max_nodes=self.config["max_vehicles"],
            node_features=num_node_features(self.config["vertex_features"]),
            max_edges=self.config["max_edges"],
            num_relations=NUM_RELATIONS,
            edge_features=len(self.config["edge_features"]),
        )
        self.action_space = spaces.Box(-1.0, 1.0, (self.config["max_vehicles"],), np.float32)

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode.

        :param seed: seeds the environment's random generator (training traffic)
        :param options: ``{"scenario": Scenario | path}`` replays an evaluation scenario in this
            episode (truncated at the scenario's duration; a later ``reset`` without it returns to
            training traffic); ``{"config": {...}}`` reconfigures first
        :return: observation and info (:mod:`envs.simulation.step_record`: the events of time 0)
        """
        gym.Env.reset(self, seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"scenario", "config"}
        if unknown:
            raise ValueError(
                f"reset options: unknown keys {sorted(unknown)}; allowed: ['config', 'scenario']"
            )
        if options.get("config"):
            self.configure(options["config"])
        self.update_metadata()
        self.define_spaces()
        cfg = self.config
        self.layout = named_layout(cfg["layout"], lateral_acceleration=float(cfg["lateral_acceleration"]))
        if self.sim is not None:
            self.sim.close()  # SUMO: one simulation per process
            self.sim = None
        self.sim = make_plant(self.layout, cfg, seed)
        scenario = options.get("scenario")
        if scenario is not None:
            if isinstance(scenario, (str, Path)):
                scenario = Scenario.load(scenario)
            if not isinstance(scenario, Scenario):
                raise ValueError(
                    f"reset options: 'scenario' must be a Scenario or a path, got {type(scenario).__name__}"
                )
            self.traffic = ScenarioTraffic(self.layout, scenario, min_gap=cfg["spawn_min_gap"])
            self._duration = scenario.duration
            entered = self.traffic.spawn(self.sim)
        else:
            spawn_probability = cfg["spawn_probability"]
            if cfg["spawn_probability_range"] is not None:
                spawn_probability = float(self.np_random.uniform(*cfg["spawn_probability_range"]))
            self.traffic = TrainingTraffic(
                self.layout,
                spawn_probability=spawn_probability,
                speed_range=tuple(cfg["initial_speed_range"]),
                length=cfg["vehicle_length"],
                width=cfg["vehicle_width"],
                min_gap=cfg["spawn_min_gap"],
                queue=cfg["spawn_queue"],
            )
            if cfg["human_share"] != 0:  # a share of 0 draws nothing: today's episodes bit for bit
                if seed is not None or self._human_rng is None:
                    self._human_rng = human_rng(self.np_random if seed is None else seed)
                self.traffic.human_rng = self._human_rng
                self.traffic.human_share = human_flags(0, cfg["human_share"], self._human_rng)[1]
            self._duration = float(cfg["duration"])
            entered = self.traffic.spawn(
                self.sim, self.np_random, probability=cfg["initial_spawn_probability"]
            )
        self.time = 0.0
        self.steps = 0
        self.done = False
        self.controlled_vehicles = []
        self.road = None
        self._collided = set()
        self._stopped_ids = _EMPTY_IDS
        self._shield = self._make_shield() if cfg["shield"] else None
        self._base = None
        if cfg["residual_base"] is not None:
            self._base = hooks.maker("residual_base")(cfg["residual_base"])
            self._base.reset(seed)
        self._scheduler = None
        if cfg["action"]["type"] in SCHEDULER_ACTION_TYPES:
            self._scheduler = hooks.maker("priority")(cfg["action"]["glide"], cfg["action"]["hold"])
            self._scheduler.reset(seed)
        self._perception = Perception.install(cfg, self.layout, self.sim, seed, self.np_random)  # faults
        self._scene = self._perceive()
        obs = build_observation(
            self._scene,
            self.observation_space,
            s_scale=cfg["s_scale"],
            d_max=cfg["d_max"],
            edge_feature_names=cfg["edge_features"],
            vertex_feature_names=cfg["vertex_features"],
        )
        zero_terms = dict.fromkeys(REWARD_TERMS, 0.0)
        info = self._make_info(StepEvents(), entered, zero_terms)
        if self.render_mode == "human":
            self.render()
        return obs, info

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """Apply one commanded acceleration per vehicle for one policy period.

        :param action: ``(max_vehicles,)`` values in ``[-1, 1]``; slot ``i`` -> vehicle ``i``
        :return: observation, reward, terminated (a collision, unless ``collision_handling`` is
            ``"remove"``), truncated (time up), info
        """
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        cfg = self.config
        sim = self.sim
        n = sim.num_vehicles
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape[0] != self.action_space.shape[0]:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {np.shape(action)}")
        if not np.isfinite(action[:n]).all():
            slot = int(np.flatnonzero(~np.isfinite(action[:n]))[0])
            raise ValueError(f"action[{slot}] is {action[slot]} (vehicle slot {slot}): actions must be finite numbers")
        a_max = cfg["max_acceleration"]
        correction = np.clip(action[:n], -1.0, 1.0)
        base = None
        if self._scheduler is not None:
            acc = self._scheduled(correction)
        elif self._base is not None:
            base = np.asarray(self._base.act(self._scene), dtype=float).reshape(n)
            acc = np.clip(base + cfg["residual_scale"] * a_max * correction, -a_max, a_max)
        else:
            acc = correction * a_max
        proposal = acc
        if self._shield is not None:
            acc = self._shield.check(self._scene, proposal)
        shield_gap = float(np.abs(proposal - acc).sum()) / a_max
        if self._scheduler is not None:
            acc = self._as_commanded(acc)
        if sim.human.any() and not sim.drives_humans:  # human drivers ignore every command: they drive by the rules,
            # their command rounded as a planner's is in an evaluation (all human = PR bit for bit)
            acc = np.where(sim.human, self._as_commanded(self._human_accelerations()), acc)
        remove = cfg["collision_handling"] == "remove"
        events = sim.step(acc, remove_collided=remove)
        kept = events.kept
        n_kept = int(kept.sum())  # survivors keep their order and lead the arrays
        entered = self.traffic.spawn(sim, self.np_random)
        self.time = sim.time
        self.steps += 1
        self._scene = self._perceive(events.kept, acc)
        scene = self._truth
        dmin = min_mahalanobis(scene)
        obs = build_observation(
            self._scene,
            self.observation_space,
            s_scale=cfg["s_scale"],
            d_max=cfg["d_max"],
            min_distance=dmin if self._scene is scene else min_mahalanobis(self._scene),
            edge_feature_names=cfg["edge_features"],
            vertex_feature_names=cfg["vertex_features"],
        )
        collision = events.collisions.shape[0] > 0
        terms = reward_terms(
            speed=scene.speed[:n_kept],
            speed_limit=scene.speed_limit[:n_kept],
            acceleration=acc[kept],
            a_max=cfg["max_acceleration"],
            min_distance=dmin[:n_kept],
            collision=collision,
            proximity_threshold=cfg["proximity_threshold"],
        )
        new_stops = np.setdiff1d(events.stopped, self._stopped_ids)
        if new_stops.size:
            self._stopped_ids = np.union1d(self._stopped_ids, new_stops)
        terms.update(
            task_reward_terms(
                speed=scene.speed,
                speed_limit=scene.speed_limit,
                dt=1.0 / cfg["policy_frequency"],
                waiting=self.traffic.waiting,
                crossed=events.crossed.size,
                new_stops=new_stops.size,
                shield_gap=shield_gap,
            )
        )
        info = self._make_info(events, entered, terms)
        # Survivors keep their order and lead the rows, new vehicles follow: where each vertex was before.
        info[VERTEX_ORIGIN] = np.concatenate([np.flatnonzero(kept), np.full(len(entered), -1)])
        if self._shield is not None:
            overridden = self._shield.last_overridden
            info["shield_overridden"] = int(overridden.sum())
            info["shield_intervention_rate"] = float(overridden.mean()) if n else 0.0
            info["executed_action"] = self._executed_action(acc, base, correction, overridden)
        record = info["record"]
        self._collided = set(record.collided.tolist())
        reward = record.reward
        terminated = bool(collision) and not remove
        truncated = bool(self.time >= self._duration - 1e-9) and not terminated
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, truncated, info

    def _make_info(self, events: StepEvents, entered: np.ndarray, terms: dict[str, float]) -> dict[str, Any]:
        """The step's :class:`~envs.simulation.step_record.StepRecord` and the ``info`` that carries it."""
        lay, sim = self.layout, self.sim
        record = StepRecord(
            time=float(sim.time),
            entered=np.asarray(entered, np.int64),
            crossed=events.crossed,
            removed=events.removed,
            stopped=events.stopped,
            governed=events.governed,
            collisions=events.collisions,
            num_vehicles=sim.num_vehicles,
            waiting=int(self.traffic.waiting),
            reward_terms=terms,
            reward_weighted=weighted(terms, self.config["reward_weights"]),
            moved=events.moved,
            speeds=events.speeds,
            substep=1.0 / sim.simulation_frequency,
            lost=events.lost,
        )
        info = record.info()
        # For users only (the metrics read these facts from the scenes): the new vehicles are the last rows.
        rows = range(sim.num_vehicles - len(entered), sim.num_vehicles)
        info["vehicles"] = {
            int(sim.vehicle_id[r]): {
                "route": lay.route_names[sim.route[r]],
                "priority": int(lay.priority[sim.route[r]]),
                "maneuver": MANEUVERS[lay.maneuver[sim.route[r]]],
                "time": float(sim.appearance_time[r]),
            }
            for r in rows  # once per new vehicle
        }
        return info

    def _scheduled(self, scores: np.ndarray) -> np.ndarray:
        """Glide's accelerations with its order shifted by the scores (``action`` ``"priority"``) or its
        advice windows moved by them (``"advice"``, never below 0 m)."""
        action = self.config["action"]
        return self._scheduler.schedule(self._scene, action["type"], action["scale"] * scores)

    def _as_commanded(self, acc: np.ndarray) -> np.ndarray:
        """Accelerations as a planner's command reaches the simulation in an evaluation (through the
        float32 action of :meth:`accelerations_to_action`), so that training and evaluation agree bit for bit."""
        a_max = self.config["max_acceleration"]
        action = np.clip(acc / a_max, -1.0, 1.0).astype(np.float32)
        return np.clip(action.astype(np.float64), -1.0, 1.0) * a_max

    def _human_accelerations(self) -> np.ndarray:
        """The human driver model's accelerations for every row of the current scene."""
        if self._human_model is None:
            self._human_model = hooks.maker("human")()
        return np.asarray(self._human_model.act(self._scene.copy()), float).reshape(self.sim.num_vehicles)

    def _make_shield(self):
        cfg = self.config
        return hooks.maker("shield")(
            simulation_frequency=cfg["simulation_frequency"],
            max_speed=cfg["max_speed"],
            governor_deceleration=cfg["governor_deceleration"],
        )

    def _executed_action(
        self, acc: np.ndarray, base: np.ndarray | None, correction: np.ndarray, overridden: np.ndarray
    ) -> np.ndarray:
        """The padded action to store for this step: the policy's own where the shield kept its
        proposal, and where it overrode it the action that would have commanded the shield's ``acc``.

        A residual correction that the acceleration bounds clip (any positive one over full throttle)
        is stored as proposed, as SB3 stores an action that an environment clips: storing the clipped
        value would hide those actions from the critic, which then extrapolates into them and drives
        the actor there (the feature-trained residual policies saturated at +1 so).
        """
        a_max = self.config["max_acceleration"]
        action = np.zeros(self.action_space.shape, np.float32)
        if self._scheduler is not None:  # a score, not an acceleration: the shield's override is no score
            action[: acc.size] = correction
            return action
        if base is None:
            shield = acc / a_max
        else:
            shield = (acc - base) / (self.config["residual_scale"] * a_max)
        action[: acc.size] = np.clip(np.where(overridden, shield, correction), -1.0, 1.0)
        return action

    def close(self) -> None:
        """Release the plant (SUMO's simulation) and the viewer."""
        if self.sim is not None:
            self.sim.close()
        super().close()

    # ------------------------------------------------------------------ public helpers
    @property
    def scheduler(self) -> Any:
        """Glide's scheduler that the ``"priority"`` and ``"advice"`` actions drive (``None`` for accelerations):
        a search that labels those actions plans from its memory (:mod:`envs.planners.expert`)."""
        return self._scheduler

    def scene(self) -> Scene:
        """The current snapshot of all vehicles (row ``i`` = vertex ``i`` = action slot ``i``)."""
        if self._scene is None:
            raise RuntimeError("call reset() first")
        return self._scene

    def true_scene(self) -> Scene:
        """The true snapshot, which the rewards and the metrics read: the :meth:`scene` itself without faults."""
        if self._truth is None:
            raise RuntimeError("call reset() first")
        return self._truth

    def perception_errors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The true errors of the measurements :meth:`scene` rests on, per row
        (:attr:`envs.simulation.perception.Perception.errors`: arcs [m] and speeds [m/s] against the truth at their
        capture, ages [s]), which only the environment knows; ``None`` without faults (the scene is the truth)."""
        return None if self._perception is None else self._perception.errors

    def _perceive(self, kept: np.ndarray | None = None, commanded: np.ndarray | None = None) -> Scene:
        """Read the truth from the plant and return what the planners perceive of it (the truth without faults).

        :param kept: after a step, its ``StepEvents.kept``; ``None``: no time passed (reset, placed vehicles)
        :param commanded: the step's commands (rows before it), which a tracker takes as input
        """
        self._truth = self.sim.scene()
        if self._perception is None:
            return self._truth
        return self._perception.observe(self.sim, kept, commanded)

    def accelerations_to_action(self, acc: np.ndarray) -> np.ndarray:
        """Turn accelerations for the current vehicles into this environment's padded action.

        :param acc: ``(n,)`` accelerations [m/s^2] for the ``n`` vehicles of :meth:`scene`
        :return: ``(max_vehicles,)`` float32 action in ``[-1, 1]`` (zeros in padded slots)
        """
        acc = np.asarray(acc, dtype=np.float64).reshape(-1)
        n = self.scene().num_vehicles
        if acc.shape[0] != n:
            raise ValueError(f"expected {n} accelerations (one per vehicle), got {acc.shape[0]}")
        action = np.zeros(self.action_space.shape, np.float32)
        action[:n] = np.clip(acc / self.config["max_acceleration"], -1.0, 1.0)
        return action

    def place_vehicles(
        self,
        routes: list[str] | np.ndarray,
        arc: np.ndarray,
        speed: np.ndarray,
        vehicle_id: np.ndarray | None = None,
        length: np.ndarray | float | None = None,
        width: np.ndarray | float | None = None,
        human: np.ndarray | bool | None = None,
    ) -> Scene:
        """Put vehicles into the current episode by hand (tests, hand-built situations).

        :param routes: route names (or route indices) of the new vehicles
        :param arc: their centre positions along the routes [m from the route start]
        :param speed: their speeds [m/s]
        :param vehicle_id: their ids (default: ``1_000_000`` upwards, unused by traffic)
        :param length: lengths [m] (default: ``vehicle_length``)
        :param width: widths [m] (default: ``vehicle_width``)
        :param human: human-driven vehicles (default: none; see ``human_share``)
        :return: the new scene (the next observation of ``step`` is built from the new state)
        """
        if self.sim is None:
            raise RuntimeError("call reset() first")
        route = np.array(
            [self.layout.route_id(r) if isinstance(r, str) else int(r) for r in routes], np.int64
        )
        if vehicle_id is None:
            start = max(1_000_000, int(self.sim.vehicle_id.max(initial=-1)) + 1)
            vehicle_id = np.arange(start, start + route.size)
        self.sim.add(
            route,
            np.asarray(speed, float),
            np.asarray(vehicle_id),
            self.config["vehicle_length"] if length is None else length,
            self.config["vehicle_width"] if width is None else width,
            arc=np.asarray(arc, float),
            human=human,
        )
        self._scene = self._perceive()
        return self._scene

    def set_spawn_probability(self, probability: float) -> None:
        """Change the training spawn probability per lane and step (a curriculum calls this).

        :param probability: in ``[0, 1]``; applies from the next step on and to later episodes
        """
        self.configure({"spawn_probability": probability})
        if isinstance(self.traffic, TrainingTraffic):
            self.traffic.spawn_probability = float(probability)

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """Draw the road and the vehicles with highway-env's viewer (major-road vehicles blue,
        minor-road vehicles yellow, vehicles in a collision red)."""
        if self.sim is None:
            return None
        if self.road is None:
            self.road = Road(network=self.layout.network, np_random=self.np_random, record_history=False)
        scene = self.true_scene()  # the world as it is, not as it is perceived
        collided = self._collided
        vehicles = []
        for i in range(scene.num_vehicles):  # rendering only: highway-env vehicles one by one
            v = Vehicle(None, scene.position[i], float(scene.heading[i]), float(scene.speed[i]))
            v.LENGTH = float(scene.length[i])
            v.WIDTH = float(scene.width[i]) if scene.width is not None else 2.0
            v.color = VehicleGraphics.BLUE if scene.priority[i] == MAJOR else VehicleGraphics.YELLOW
            if int(scene.vehicle_id[i]) in collided:
                v.color = VehicleGraphics.RED
            vehicles.append(v)
        self.road.vehicles = vehicles
        return super().render()


class CoopIntersection4WayEnv(CoopIntersectionEnv):
    """The paper's synthetic four-way intersection (major road west-east, minor road north-south)."""

    LAYOUT = "4way"


class CoopIntersection3WayEnv(CoopIntersectionEnv):
    """A T junction: major road west-east, minor arm to the south (merging and crossing)."""

    LAYOUT = "3way"


class CoopIntersectionInDEnv(CoopIntersectionEnv):
    """Approximation of the inD four-way: priority road west-east with isolated left-turn lanes."""

    LAYOUT = "inD"
