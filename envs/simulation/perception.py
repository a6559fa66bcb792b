"""What the planners and the shield perceive of the truth under the fault model (:mod:`envs.simulation.faults`).

The truth stays in the plant: the metrics and the collision checks read it. :class:`Perception` turns the plant's
columns into the perceived ones each policy step (the state of ``latency`` ago, off by the perception errors, held
while messages are lost, or a tracker's estimate of it) and builds the perceived :class:`~envs.simulation.scene.Scene`
through the same door as the true one (a :class:`~envs.simulation.engine.Simulation` table holding the perceived
columns), so that ``s``, ``dist_to_entry``, ``dist_to_exit``, the poses, the speed limits, the leaders and the gaps
all agree with the perceived arcs. The perceived scene carries per-vehicle ``arc_std``, ``speed_std`` and ``age``.

With no fault configured there is no :class:`Perception`: the scene the planners see is the true one, the same arrays.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from envs.simulation.engine import Simulation, integrate
from envs.simulation.faults import LOSS, POSITION, SPEED, Actuator, ById, FaultDraws, faults_active
from envs.simulation.layouts import Layout
from envs.simulation.scene import Scene
from envs.simulation.tracker import ArcTracker

# Added to the episode's seed so that the fault draws are a stream of their own.
FAULT_SEED_OFFSET = 0x5EED_FA17


class Perception:
    """The perceived scene of each policy step (see the module docstring).

    :param faults: a checked ``faults`` setting (:func:`envs.simulation.faults.fault_config`)
    :param layout: the intersection
    :param config: the environment's resolved configuration (the table of perceived columns is built from it)
    :param seed: the episode's fault seed
    """

    def __init__(self, faults: dict[str, Any], layout: Layout, config: dict[str, Any], seed: int) -> None:
        self.faults = faults
        self.layout = layout
        self.draws = FaultDraws(seed)
        self.table = Simulation.from_config(layout, config)  # the perceived columns, read through scene()
        self.dt = 1.0 / config["policy_frequency"]
        self.h = 1.0 / config["simulation_frequency"]
        self.max_speed = float(config["max_speed"])
        self.governor_deceleration = float(config["governor_deceleration"])
        self.memory = ById()  # per vehicle: error states, held measurement and its capture time
        self.tracker = None
        if faults["tracker"]:
            tau = faults["position_tau"]
            self.tracker = ArcTracker(
                faults["position_sigma"], faults["speed_sigma"], faults["process_noise"], faults["latency"],
                correlation=math.exp(-self.dt / tau) if tau > 0 else 0.0,
            )  # fmt: skip
        self.step_index = 0
        # The true errors of the measurements that the last perceived scene rests on, per row: arc [m] and speed
        # [m/s] against the truth at their capture, and their ages [s] (what declared bounds promise; a tracker's
        # estimate is built from these).
        self.errors: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0), np.zeros(0))
        # The planner side's replay of the actuation (the same model as the plant's): the acceleration each vehicle
        # realises, from the commands it was sent.
        self.replica = None
        if faults["latency"] > 0 or faults["lag"] > 0:
            substeps = int(config["simulation_frequency"]) // int(config["policy_frequency"])
            self.replica = Actuator(faults["latency"], faults["lag"], substeps, self.h)

    @classmethod
    def install(
        cls, config: dict[str, Any], layout: Layout, plant: Any, seed: int | None, rng: Any
    ) -> Perception | None:
        """The perception of an episode, with the plant's actuator set (latency, lag), or ``None`` without faults.

        :param config: the environment's resolved configuration (its ``faults``)
        :param layout: the intersection
        :param plant: the episode's plant (its ``actuator`` is set where latency or lag is configured)
        :param seed: the reset's seed; ``None``: one is drawn from ``rng``
        :param rng: the environment's generator (``np_random``)
        """
        faults = config.get("faults")
        if not faults_active(faults):
            return None
        if faults["latency"] > 0 or faults["lag"] > 0:
            if not hasattr(plant, "actuator"):  # it would ignore them silently
                raise ValueError(
                    f"config key 'faults': latency and lag need a plant that applies an actuator (the builtin "
                    f"simulation); {type(plant).__name__} has none"
                )
            h = 1.0 / plant.simulation_frequency
            plant.actuator = Actuator(faults["latency"], faults["lag"], plant.substeps, h)
        if seed is None:
            seed = int(rng.integers(1 << 62))
        return cls(faults, layout, config, int(seed) + FAULT_SEED_OFFSET)

    # ------------------------------------------------------------------ one step
    def observe(self, plant: Any, kept: np.ndarray | None = None, commanded: np.ndarray | None = None) -> Scene:
        """The perceived scene now: after a policy step (``kept`` given) or without time passing (reset, a hand-made
        change: known vehicles keep what was perceived, new ones are measured).

        :param plant: the plant after the step (its columns and ``last_trajectory``)
        :param kept: ``(m,)`` bool over the rows before the step: still in the scene (they lead the rows now)
        :param commanded: ``(m,)`` the step's commanded accelerations (rows before the step), for the tracker
        """
        f = self.faults
        ids = plant.vehicle_id
        n = ids.size
        dt = self.dt if kept is not None else 0.0
        if kept is not None:
            self.step_index += 1
        step = self.step_index
        arc_then, speed_then = self._state_latency_ago(plant, kept)
        rows, known = self.memory.find(ids)
        ex = self._error(rows, known, "ex", f["position_sigma"], f["position_tau"], ids, step, POSITION, dt)
        ev = self._error(rows, known, "ev", f["speed_sigma"], f["speed_tau"], ids, step, SPEED, dt)
        z_arc = arc_then + _clip(ex, f["position_bound"])
        z_speed = np.maximum(speed_then + _clip(ev, f["speed_bound"]), 0.0)
        held_age = plant.time - self.memory.get("captured", rows, known, plant.time)
        received = ~known
        if dt > 0:  # a new message from every known vehicle, unless lost (never beyond max_age)
            lost = self.draws.uniform(ids, step, LOSS) < f["loss"]
            received |= ~(lost & (held_age <= f["max_age"] + 1e-9))
        captured = plant.time - f["latency"]
        e_arc = np.where(received, z_arc - arc_then, self.memory.get("e_arc", rows, known, 0.0))
        e_speed = np.where(received, z_speed - speed_then, self.memory.get("e_speed", rows, known, 0.0))
        z_arc = np.where(received, z_arc, self.memory.get("z_arc", rows, known, 0.0))
        z_speed = np.where(received, z_speed, self.memory.get("z_speed", rows, known, 0.0))
        captured = np.where(received, captured, self.memory.get("captured", rows, known, captured))
        sent, accel, recent = self._commands(ids, rows, known, kept, commanded)
        age = plant.time - captured
        realised = None
        if self.replica is not None:
            r_rows, r_known = self.replica.memory.find(ids)
            realised = self.replica.memory.get("realised", r_rows, r_known, 0.0)
        self.errors = (e_arc, e_speed, age)
        if self.tracker is None:
            arc, speed = z_arc, z_speed
            arc_std, speed_std = np.full(n, f["position_sigma"]), np.full(n, f["speed_sigma"])
        else:
            cap = self.layout.envelope_at(plant.route, np.maximum(z_arc, 0.0), self.governor_deceleration)
            arc, speed, arc_std, speed_std = self.tracker.step(ids, dt, accel, received, z_arc, z_speed, cap, recent)
            if f["latency"] > 0:  # the estimate of when the coming commands take effect: the last ones act till then
                arc, speed, realised = self._drive(plant.route, arc, speed, sent, realised, f["latency"])
                arc_std = np.hypot(arc_std, f["latency"] * speed_std)
        self.memory.store(
            ids, ex=ex, ev=ev, z_arc=z_arc, z_speed=z_speed, e_arc=e_arc, e_speed=e_speed, captured=captured,
            sent=sent, v_seen=speed,
        )  # fmt: skip
        scene = self._scene(plant, arc, speed, arc_std, speed_std, age)
        return scene if realised is None else dataclasses.replace(scene, acceleration=realised, command=sent)

    def _commands(self, ids, rows, known, kept, commanded) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Each vehicle's last command (in flight for ``latency``), the past period's mean acceleration and that of
        its last ``latency`` seconds (``None``: the same), as the planner side models them from its commands."""
        n = ids.size
        sent = self.memory.get("sent", rows, known, 0.0)
        accel, recent = sent.copy(), None
        if kept is None or commanded is None:
            return sent, accel, recent
        m = int(kept.sum())
        sent = np.zeros(n)
        sent[:m] = np.asarray(commanded, float)[kept]
        accel = sent.copy()
        if self.replica is not None:  # latency and lag, replayed from the commands (at rest: the brakes hold)
            seen = self.memory.get("v_seen", rows, known, 0.0)
            replayed = self.replica(ids[:m], sent[:m], seen[:m])
            accel[:m] = replayed.mean(axis=0)
            last = max(1, math.ceil(self.faults["latency"] / self.h - 1e-9))  # the sub-steps of the last `latency`
            recent = accel.copy()
            recent[:m] = replayed[-last:].mean(axis=0)
        return sent, accel, recent

    def _drive(self, route, arc, speed, command, realised, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arcs, speeds and realised accelerations after ``t`` seconds of ``command`` through the actuation lag, under
        the simulation's own vehicle model (the governor)."""
        substeps = max(1, math.ceil(t / self.h - 1e-9))
        h = t / substeps
        lag = self.faults["lag"]
        decay = math.exp(-h / lag) if lag > 0 else 0.0
        mean_share = lag / h * (1.0 - decay) if lag > 0 else 0.0
        r = np.where(speed <= 0.0, np.maximum(realised, 0.0), realised)
        acc = np.empty((substeps, arc.size))
        for k in range(substeps):  # a loop over time (two sub-steps), vectorized over vehicles
            acc[k] = command + (r - command) * mean_share
            r = command + (r - command) * decay
        end = self.layout.length[route] - 1e-6
        v, x, _ = integrate(
            self.layout, route, np.clip(arc, 0.0, end), np.clip(speed, 0.0, self.max_speed), acc, substeps, h,
            self.max_speed, self.governor_deceleration,
        )  # fmt: skip
        return x[-1], v[-1], r

    def _error(self, rows, known, name, sigma, tau, ids, step, stream, dt) -> np.ndarray:
        """Each vehicle's error now: a stationary Gauss-Markov process (a fresh draw for a new vehicle)."""
        n = ids.size
        if sigma == 0:
            return np.zeros(n)
        previous = self.memory.get(name, rows, known, 0.0)
        if dt == 0:
            rho = 1.0
        else:
            rho = math.exp(-dt / tau) if tau > 0 else 0.0
        fresh = sigma * self.draws.normal(ids, step, stream)
        return np.where(known, rho * previous + math.sqrt(1.0 - rho * rho) * fresh, fresh)

    def _state_latency_ago(self, plant: Any, kept: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The true arcs and speeds of ``latency`` ago: on the plant's sub-step trajectory of the last step where
        there is one (a constant acceleration between sub-steps), run back at constant speed elsewhere (a vehicle
        that has just appeared)."""
        lat = self.faults["latency"]
        arc, speed = plant.arc, plant.speed
        if lat == 0:
            return arc, speed
        arc_then = np.maximum(arc - speed * lat, 0.0)
        speed_then = speed.copy()
        trajectory = getattr(plant, "last_trajectory", None)
        if kept is not None and trajectory is not None and trajectory[0].shape[1] == kept.size:
            v_tr, x_tr = trajectory[0][:, kept], trajectory[1][:, kept]
            substeps = v_tr.shape[0] - 1
            u = substeps - lat / self.h
            j = min(max(int(math.floor(u + 1e-9)), 0), substeps - 1)
            tau = (u - j) * self.h
            a = (v_tr[j + 1] - v_tr[j]) / self.h
            m = v_tr.shape[1]
            arc_then[:m] = x_tr[j] + v_tr[j] * tau + 0.5 * a * tau * tau
            speed_then[:m] = v_tr[j] + a * tau
        return arc_then, speed_then

    def _scene(self, plant, arc, speed, arc_std, speed_std, age) -> Scene:
        """The scene of the perceived columns (every derived field from the perceived arcs)."""
        end = self.layout.length[plant.route] - 1e-6
        self.table.set_state(
            plant.time,
            plant.route,
            plant.vehicle_id,
            np.clip(arc, 0.0, end),
            np.clip(speed, 0.0, self.max_speed),
            plant.length,
            plant.width,
            plant.human,
        )
        return dataclasses.replace(self.table.scene(), arc_std=arc_std, speed_std=speed_std, age=age)


def _clip(error: np.ndarray, bound: float | None) -> np.ndarray:
    return error if bound is None else np.clip(error, -bound, bound)
