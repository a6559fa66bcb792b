"""Free-flow reference times against closed-form trips on hand-made speed-limit profiles."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from envs.simulation.free_flow import free_flow_table, time_at
from envs.simulation.layouts import build_layout

DS = 0.5


def _layout(*limits: np.ndarray) -> SimpleNamespace:
    """A stand-in layout: one route per limit profile (sampled every DS metres)."""
    return SimpleNamespace(ds=DS, speed_limit=np.stack(limits))


def _trip(layout, route, start, v0, distance, a=5.0, b=5.0):
    table = free_flow_table(layout, np.array([route]), np.array([start]), np.array([v0]), a, b)
    return float(time_at(table, np.array([distance]), DS)[0])


def test_cruising_at_the_limit_takes_distance_over_limit():
    lay = _layout(np.full(400, 10.0))
    assert _trip(lay, 0, 2.5, 10.0, 100.0) == pytest.approx(10.0)


def test_acceleration_from_the_initial_speed():
    lay = _layout(np.full(400, 10.0))
    # 6 -> 10 m/s at 2 m/s^2: 2 s over 16 m, then 84 m at 10 m/s
    assert _trip(lay, 0, 0.0, 6.0, 100.0, a=2.0) == pytest.approx(2.0 + 8.4, rel=1e-3)
    assert _trip(lay, 0, 0.0, 0.0, 100.0, a=2.0) == pytest.approx(5.0 + 75.0 / 10.0, rel=1e-3)


def test_brakes_in_time_for_a_lower_limit_ahead():
    """10 m/s, then 6 m/s from 100 m on: braking at b starts (100 - 6.4) m in, so the trip to 150 m
    takes 93.6/10 + 0.8 + 50/6 s, more than a trip that slows only at the lower limit."""
    limits = np.full(400, 10.0)
    limits[200:] = 6.0
    lay = _layout(limits)
    expected = 93.6 / 10.0 + (10.0 - 6.0) / 5.0 + 50.0 / 6.0
    assert _trip(lay, 0, 0.0, 10.0, 150.0) == pytest.approx(expected, rel=2e-3)
    # the time never decreases along the route, and is zero at the start
    table = free_flow_table(lay, np.array([0]), np.array([0.0]), np.array([10.0]), 5.0, 5.0)
    assert table[0, 0] == 0.0 and (np.diff(table[0]) > 0).all()


def test_vectorized_over_vehicles_and_nan_distance():
    lay = build_layout("4way")
    route = np.arange(lay.num_routes)
    start = np.full(route.size, 2.5)
    table = free_flow_table(lay, route, start, lay.speed_limit[route, 0], 5.0, 5.0)
    times = time_at(table, lay.exit_arc[route] - start, lay.ds)
    one = [_trip(lay, r, 2.5, lay.speed_limit[r, 0], lay.exit_arc[r] - 2.5) for r in route]
    np.testing.assert_allclose(times, one)
    # never faster than the highest limit of the route
    assert (times >= (lay.exit_arc[route] - start) / lay.speed_limit.max(axis=1) - 1e-9).all()
    assert np.isnan(time_at(table[:1], np.array([np.nan]), lay.ds)[0])
    with pytest.raises(ValueError, match="positive"):
        free_flow_table(lay, route, start, start, 0.0, 5.0)
