"""The evaluation's time left: priced per planner from warm runs, stable from the first runs."""

from __future__ import annotations

import heapq

import numpy as np
import pytest

from envs.evaluation.progress import RunClock, format_eta, interleaved


def test_interleaved_hands_out_every_planner_per_scenario():
    order = interleaved(3, 2)  # planner-major indices p * 2 + s
    assert order == [0, 2, 4, 1, 3, 5] and sorted(order) == list(range(6))


def test_cold_runs_are_not_samples_and_an_unmeasured_planner_leaves_the_time_unknown():
    clock = RunClock(["a", "a", "a", "b", "b"], [100, 100, 100, 100, 50], workers=1)
    clock.record(0, 60.0, warm=False)  # loaded the planner: no sample
    assert clock.remaining_s() is None and format_eta(None) == "?"
    clock.record(1, 10.0)  # a: 0.1 s per simulated s; b not measured: no guess from a's rate
    assert clock.remaining_s() is None
    clock.record(3, 40.0)  # b: 0.4 s per simulated s
    assert clock.remaining_s() == pytest.approx(0.1 * 100 + 0.4 * 50)
    clock.record(2, 10.0)
    clock.record(4, 20.0)
    assert clock.remaining_s() == 0.0 and format_eta(65) == "01:05"


def test_time_left_is_shared_among_the_workers_but_not_below_one_run_each():
    clock = RunClock(["a"] * 4, [10.0] * 4, workers=8)
    clock.record(0, 5.0)
    assert clock.remaining_s() == pytest.approx(3 * 5.0 / 3)  # 3 runs left on 8 workers: 3 at once


def _simulate(costs, cold, scenarios, workers, duration=100.0):
    """Greedy workers running the interleaved runs; yields (index, end time, wall, warm) in completion order."""
    planners = len(costs)
    order = interleaved(planners, scenarios)
    free = [(0.0, w) for w in range(workers)]
    loaded: set = set()
    ends = []
    for i in order:
        start, w = heapq.heappop(free)
        p = i // scenarios
        warm = (w, p) in loaded
        loaded.add((w, p))
        wall = costs[p] * duration + (0.0 if warm else cold)
        ends.append((start + wall, i, wall, warm))
        heapq.heappush(free, (start + wall, w))
    return sorted(ends)


def test_the_first_estimates_are_close_where_a_plain_rate_is_off_by_far():
    # the main job's shape: 7 planners, the cheap rules first, the learned planner behind the shield 20 x dearer,
    # every worker's first run of a planner 8 s longer (loading, compiling)
    costs = [0.002, 0.002, 0.004, 0.003, 0.01, 0.02, 0.04]
    scenarios, workers = 100, 2
    ends = _simulate(costs, cold=8.0, scenarios=scenarios, workers=workers)
    total = ends[-1][0]
    keys = [str(i // scenarios) for i in range(len(costs) * scenarios)]
    clock = RunClock(keys, [100.0] * len(keys), workers)
    errors, plain, first = [], [], None
    for n, (end, i, wall, warm) in enumerate(ends, start=1):
        clock.record(i, wall, warm)
        left = clock.remaining_s()
        if left is not None and first is None:
            first = n
        if left is not None and n <= first + 10 * len(costs):  # the first estimates, a tenth of the job
            errors.append(abs(end + left - total) / total)
            plain.append(abs(end + (len(ends) - n) * end / n - total) / total)  # runs left x time per run so far
    assert first <= 0.05 * len(ends)  # an estimate within the first 5 % of the runs
    assert max(errors) < 0.2, max(errors)
    assert np.median(plain) > 3 * np.median(errors), (np.median(plain), np.median(errors))
