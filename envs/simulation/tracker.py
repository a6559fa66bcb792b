"""A tracker per vehicle along its path: a Kalman filter on ``[arc, speed]``, vectorized over vehicles.

The model is constant acceleration over a policy period with the commanded acceleration as its input (the planner
side knows what it commanded), plus white acceleration noise (``process_noise``) for what the command does not say
(lag, the governor, a stop). A measurement is of the state ``latency`` seconds ago: it enters through
``H = [[1, -L], [0, 1]]`` (the state now, run back by ``L``), so the estimate is of the scene's own time. A vehicle
whose message is lost is predicted forward and its uncertainty grows. The 2x2 algebra is written out element by
element (three arrays for the symmetric covariance), so that every step is a few array operations for all vehicles.

A bias held for a second (the correlated position error) is not noise: the filter smooths the white part and cannot
see the held part.
"""

from __future__ import annotations

import numpy as np

from envs.simulation.faults import ById

# Floors of the measurement variances (a zero variance would make the update singular) [m^2], [(m/s)^2].
_MIN_VAR = 1e-4


class ArcTracker:
    """Per-vehicle estimates of the position along the path and the speed, keyed by vehicle id.

    :param position_sigma: standard deviation of a position measurement [m]
    :param speed_sigma: standard deviation of a speed measurement [m/s]
    :param process_noise: standard deviation of the unmodelled acceleration [m/s^2]
    :param latency: age of every measurement when it arrives [s]
    :param correlation: correlation of a vehicle's position error from one message to the next (``rho``)
    """

    def __init__(
        self, position_sigma: float, speed_sigma: float, process_noise: float, latency: float, correlation: float = 0.0
    ) -> None:
        # A correlated error averages out slowly: n samples with step correlation rho hold as much as n (1 - rho) /
        # (1 + rho) independent ones, so the filter takes each position as that much noisier.
        inflation = (1.0 + correlation) / (1.0 - correlation) if correlation < 1.0 else 1e6
        self.rx = max(float(position_sigma) ** 2 * inflation, _MIN_VAR)
        self.rv = max(float(speed_sigma) ** 2, _MIN_VAR)
        self.q = float(process_noise) ** 2
        self.latency = float(latency)
        self.tracks = ById()

    def reset(self) -> None:
        """Forget every vehicle."""
        self.tracks = ById()

    def step(
        self,
        vehicle_id: np.ndarray,
        dt: float,
        accel: np.ndarray,
        received: np.ndarray,
        z_arc: np.ndarray,
        z_speed: np.ndarray,
        cap: np.ndarray | float = np.inf,
        recent: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predict every known vehicle over ``dt`` and update those with a new message; start the new ones.

        :param vehicle_id: ``(n,)`` the vehicles in the scene now
        :param dt: time since the last step [s]
        :param accel: ``(n,)`` mean commanded acceleration over that time [m/s^2]
        :param received: ``(n,)`` bool: a message arrived this step (always true for a vehicle not tracked yet)
        :param z_arc: ``(n,)`` measured arcs (of ``latency`` ago) [m]
        :param z_speed: ``(n,)`` measured speeds [m/s]
        :param cap: ``(n,)`` each vehicle's speed cap where it is (the governor's envelope) [m/s]
        :param recent: ``(n,)`` mean acceleration over the last ``latency`` seconds, which run a measurement back to
            now (default ``accel``; with latency, the newest command has applied since the period's first ``latency``)
        :return: ``(n,)`` estimated arcs, speeds, and their standard deviations
        """
        rows, known = self.tracks.find(vehicle_id)
        x = self.tracks.get("x", rows, known, 0.0)
        v = self.tracks.get("v", rows, known, 0.0)
        pxx = self.tracks.get("pxx", rows, known, 0.0)
        pxv = self.tracks.get("pxv", rows, known, 0.0)
        pvv = self.tracks.get("pvv", rows, known, 0.0)
        x, v = advance(x, v, accel, dt, cap)
        q = self.q
        pxx, pxv, pvv = (
            pxx + 2 * dt * pxv + dt * dt * pvv + q * dt**3 / 3,
            pxv + dt * pvv + q * dt**2 / 2,
            pvv + q * dt,
        )
        recent = accel if recent is None else recent
        x, v, pxx, pxv, pvv = self._update(x, v, pxx, pxv, pvv, recent, cap, received & known, z_arc, z_speed)
        new = ~known
        if new.any():  # a first message starts a track: the measurement run forward by the latency
            lat = self.latency
            x[new] = z_arc[new] + z_speed[new] * lat
            v[new] = z_speed[new]
            pxx[new] = self.rx + self.rv * lat * lat
            pxv[new] = self.rv * lat
            pvv[new] = self.rv
        self.tracks.store(vehicle_id, x=x, v=v, pxx=pxx, pxv=pxv, pvv=pvv)
        return x, v, np.sqrt(np.maximum(pxx, 0.0)), np.sqrt(np.maximum(pvv, 0.0))

    def _update(self, x, v, pxx, pxv, pvv, accel, cap, use, z_arc, z_speed):
        """The Kalman update where ``use``, with the measurement of ``latency`` ago (``H = [[1, -L], [0, 1]]``)."""
        lat = self.latency
        back_x, back_v = advance(x, v, accel, -lat, cap) if lat > 0 else (x, v)
        y0 = np.where(use, z_arc - back_x, 0.0)
        y1 = np.where(use, z_speed - back_v, 0.0)
        a00, a01 = pxx - lat * pxv, pxv - lat * pvv  # A = H P (its second row is [pxv, pvv])
        s00 = a00 - lat * a01 + self.rx
        s01 = a01
        s11 = pvv + self.rv
        det = s00 * s11 - s01 * s01
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        # K = A^T S^-1 (P H^T = (H P)^T)
        k00 = a00 * i00 + pxv * i01
        k01 = a00 * i01 + pxv * i11
        k10 = a01 * i00 + pvv * i01
        k11 = a01 * i01 + pvv * i11
        x = x + np.where(use, k00 * y0 + k01 * y1, 0.0)
        v = np.maximum(v + np.where(use, k10 * y0 + k11 * y1, 0.0), 0.0)
        # P - K A
        n00 = pxx - (k00 * a00 + k01 * pxv)
        n01 = pxv - (k00 * a01 + k01 * pvv)
        n11 = pvv - (k10 * a01 + k11 * pvv)
        return x, v, np.where(use, n00, pxx), np.where(use, n01, pxv), np.where(use, n11, pvv)


def advance(
    x: np.ndarray, v: np.ndarray, a: np.ndarray, t: float, cap: np.ndarray | float = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    """Arc and speed after ``t`` seconds at acceleration ``a`` (``t`` < 0 runs back); a vehicle that would pass a
    speed of 0 stops there (vehicles never drive backwards), and one at its speed cap (the governor's envelope, which
    the planner side knows from the layout) does not speed up beyond it."""
    a = np.where((a > 0) & (v >= cap - 1e-6), 0.0, a)
    v_end = v + a * t
    stops = v_end < 0
    v_end = np.maximum(v_end, 0.0)
    if t > 0:
        v_end = np.minimum(v_end, np.maximum(cap, v))
    x_end = x + 0.5 * (v + v_end) * t
    if stops.any():  # the distance to the stop, v^2 / 2|a|, in the direction of t
        with np.errstate(divide="ignore", invalid="ignore"):
            to_stop = np.where(np.abs(a) > 0, v * v / (2 * np.abs(a)), 0.0)
        x_end = np.where(stops, x + np.sign(t) * to_stop, x_end)
    return x_end, v_end
