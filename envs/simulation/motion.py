"""What a vehicle's executed motion costs: crawling, hard braking and traction energy.

These measures read only speeds that really happened (the simulation's sub-step speeds after the
planner, the shield and the speed governor; or a recorded track's speeds), never a planner's request.
They exist because a stop threshold invites creeping just above it (a planner can keep every vehicle at
0.31 m/s and report no stops): the three measures see the whole low-speed range, the braking and the
cost of every restart.

- **Slow**: a vehicle is *slow* when its speed fell below :data:`SLOW_SPEED` (2 m/s) at some sample
  (the stop threshold, :data:`envs.simulation.scene.STOP_SPEED`, is 0.3 m/s; every stopped vehicle is slow).
- **Hard-braking event**: a maximal run of consecutive samples (simulation sub-steps, or frames of a
  recorded track) of one vehicle in which its acceleration was below :data:`HARD_BRAKE_ACCELERATION`
  (-3 m/s^2) by more than :data:`HARD_BRAKE_MARGIN` (:func:`hard_braking`). Between two samples the
  acceleration is constant: ``(v[k+1] - v[k]) / h``. Two brakings separated by at least one sample that is
  not hard braking are two events; one long braking that spans several policy steps is one
  (:func:`event_starts`). The margin exists because the simulation's speed governor brakes for a lower
  limit ahead at exactly 3 m/s^2 (``governor_deceleration``), which its discretization turns into samples
  within 0.008 m/s^2 either side of -3 (measured on the 4-way layout): without the margin, rounding would
  decide whether a curve counts as hard braking.
- **Traction energy**: the time integral of the *positive* part of the power at the wheels of a
  longitudinal road-load model (no recuperation: braking and coasting cost nothing and give nothing back),
  on a flat road (:func:`wheel_power`, :func:`traction_energy`).

Energy model: PHEMlight 5 (TU Graz), ``CEP::CalcWheelPower`` without the grade term::

    P = [(m + m_load) g (f0 + f1 v) + rho / 2 c_w A v^2 + (m k_rot(v) + m_wheel + m_load) a] v

with ``v`` the speed [m/s], ``a`` the acceleration [m/s^2] and ``k_rot(v)`` the rotating-mass factor of
the engaged gear, linear in speed between the table's points (:data:`GEAR_SPEEDS`, :data:`ROTATING_MASS_FACTORS`).
Vehicle class assumed: PHEMlight's average **Euro 4 petrol passenger car** (``PC_EU4_G``). Sources of
the constants:

- ``m`` (:data:`VEHICLE_MASS`), ``m_load`` (:data:`VEHICLE_LOADING`), ``m_wheel`` (:data:`WHEEL_ROTATING_MASS`,
  "RedMassWheel"), ``c_w`` (:data:`DRAG_COEFFICIENT`), ``A`` (:data:`FRONTAL_AREA`), ``f0``, ``f1``
  (:data:`ROLLING_RESISTANCE_F0`, :data:`ROLLING_RESISTANCE_F1`, "Fr0", "Fr1") and the gear table
  ("Transm": "Speed", "RotMassF"): the vehicle file ``PC_EU4_G.PHEMLight.veh`` of PHEMlight 5, as
  distributed with Eclipse SUMO (``data/emissions/PHEMlight5/``);
- ``g`` (:data:`GRAVITY`) and ``rho`` (:data:`AIR_DENSITY`): PHEMlight 5's ``Constants.cpp``
  (``GRAVITY_CONST``, ``AIR_DENSITY_CONST``);
- the equation: PHEMlight 5's ``CEP.cpp`` (``CEP::CalcWheelPower``, ``CEP::GetRotationalCoeffecient``), in
  SUMO's ``src/foreign/PHEMlight/V5/cpp/``; PHEMlight's method: Hausberger, Rexeis, Zallinger, Luz,
  "Emission Factors from the Model PHEM for the HBEFA Version 3", TU Graz report I-20/2009.

Left out on purpose: the drive-train efficiency and the auxiliary power of PHEMlight's engine power
(the figure is energy *at the wheels*, the same for every powertrain), and the grade (the layouts are flat).
A simulated vehicle has no gears; the gear table stands for the average car's gear choice at each speed,
which makes an acceleration from low speed (first gear, ``k_rot`` 2.1) cost more than the same one at
speed, as it does in a real car.
"""

from __future__ import annotations

import numpy as np

# A vehicle whose speed fell below this is *slow* (crawling; the stop threshold is 0.3 m/s) [m/s].
SLOW_SPEED = 2.0
# An acceleration below this is hard braking [m/s^2].
HARD_BRAKE_ACCELERATION = -3.0
# ... by more than this, so that the governor's braking at exactly 3 m/s^2 never counts (module docstring) [m/s^2].
HARD_BRAKE_MARGIN = 0.05

# PHEMlight 5, PC_EU4_G.PHEMLight.veh ("VehicleData", "RollingResData"): the Euro 4 petrol passenger car.
VEHICLE_MASS = 1193.7  # "Mass" [kg]
VEHICLE_LOADING = 179.7  # "Loading" [kg]
WHEEL_ROTATING_MASS = 38.8  # "RedMassWheel": the wheels' rotational inertia as a mass [kg]
DRAG_COEFFICIENT = 0.3745  # "Cw" [1]
FRONTAL_AREA = 2.12  # "A" [m^2]
ROLLING_RESISTANCE_F0 = 0.0095104  # "Fr0" [1]
ROLLING_RESISTANCE_F1 = 7.08e-05  # "Fr1" [s/m]: the speed-proportional rolling resistance
# "TransmissionData"/"Transm": the table's speeds ("Speed", in km/h there) and rotating-mass factors ("RotMassF").
GEAR_SPEEDS_KMH = np.array(
    [0.0, 11.161903925181518, 29.412189004603665, 50.349467492985347, 70.242619060656054, 107.97223660963981, 250.0]
)  # [km/h]
GEAR_SPEEDS = GEAR_SPEEDS_KMH / 3.6  # [m/s]
ROTATING_MASS_FACTORS = np.array(
    [2.1106531442153624, 2.1106531442153624, 1.3550542766263412, 1.1605588206788657, 1.0925309339359672,
     1.0598062620163269, 1.0598062620163269]
)  # fmt: skip
# PHEMlight 5, Constants.cpp.
GRAVITY = 9.81  # GRAVITY_CONST [m/s^2]
AIR_DENSITY = 1.182  # AIR_DENSITY_CONST [kg/m^3]

# Three-point Gauss-Legendre rule on [0, 1]: exact for polynomials of degree 5, so for the power along a
# sample with constant acceleration (a cubic in time) where it keeps one sign and one gear segment.
_NODES = 0.5 + 0.5 * np.sqrt(0.6) * np.array([-1.0, 0.0, 1.0])
_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0


def rotating_mass_factor(speed: np.ndarray) -> np.ndarray:
    """PHEMlight's rotating-mass factor ``k_rot(v)`` of the gear engaged at each speed.

    :param speed: speeds [m/s], any shape
    :return: the factors, linear between the table's speeds and constant beyond its ends
    """
    return np.interp(speed, GEAR_SPEEDS, ROTATING_MASS_FACTORS)


def wheel_power(speed: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
    """Power at the wheels [W] of the model in the module docstring, negative when braking.

    :param speed: speeds [m/s]
    :param acceleration: accelerations [m/s^2] (broadcast against ``speed``)
    :return: the power, the broadcast shape
    """
    v = np.asarray(speed, float)
    a = np.asarray(acceleration, float)
    road_mass = VEHICLE_MASS + VEHICLE_LOADING
    inertia = VEHICLE_MASS * rotating_mass_factor(v) + WHEEL_ROTATING_MASS + VEHICLE_LOADING
    force = (
        road_mass * GRAVITY * (ROLLING_RESISTANCE_F0 + ROLLING_RESISTANCE_F1 * v)
        + 0.5 * AIR_DENSITY * DRAG_COEFFICIENT * FRONTAL_AREA * v**2
        + inertia * a
    )
    return force * v


def traction_energy(v0: np.ndarray, v1: np.ndarray, h: float | np.ndarray) -> np.ndarray:
    """Traction energy [J] of samples whose speed goes linearly from ``v0`` to ``v1`` in ``h`` seconds (the
    constant acceleration between two sub-steps): the integral of the positive wheel power.

    The integral is a three-point Gauss-Legendre rule over each sample, exact wherever the power keeps its
    sign and the gear table one segment during the sample.

    :param v0: speeds at the samples' starts [m/s], any shape
    :param v1: speeds at their ends [m/s], the same shape
    :param h: the samples' durations [s] (a number or the same shape)
    :return: the energy of each sample, ``v0``'s shape
    """
    v0 = np.asarray(v0, float)
    v1 = np.asarray(v1, float)
    h = np.asarray(h, float)
    acceleration = (v1 - v0) / h
    speed = v0[..., None] + (v1 - v0)[..., None] * _NODES  # (..., 3) along each sample
    power = np.maximum(wheel_power(speed, acceleration[..., None]), 0.0)
    return h * (power @ _WEIGHTS)


def hard_braking(acceleration: np.ndarray) -> np.ndarray:
    """Whether each acceleration is hard braking: below :data:`HARD_BRAKE_ACCELERATION` by more than
    :data:`HARD_BRAKE_MARGIN`.

    :param acceleration: accelerations [m/s^2], any shape
    :return: bool, the same shape
    """
    return np.asarray(acceleration, float) < HARD_BRAKE_ACCELERATION - HARD_BRAKE_MARGIN


def event_starts(flag: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """Where a maximal run of flagged samples of one vehicle begins (one event per run).

    :param flag: ``(m,)`` bool per sample (e.g. :func:`hard_braking`)
    :param vehicle: ``(m,)`` the vehicle of each sample; a vehicle's samples are contiguous and in time order
    :return: ``(m,)`` bool: flagged, and the vehicle's first sample or the previous sample not flagged
    """
    flag = np.asarray(flag, bool)
    vehicle = np.asarray(vehicle)
    follows = np.zeros(flag.shape, bool)
    follows[1:] = flag[:-1] & (vehicle[1:] == vehicle[:-1])
    return flag & ~follows
