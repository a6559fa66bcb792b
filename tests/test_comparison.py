"""Paired differences against the strongest baseline, on hand-made metrics rows."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from envs.evaluation.comparison import PAIRED_COLUMNS, paired_differences, strongest_baseline
from sb3_graph.aggregate import bootstrap_interval


def _runs(flows: dict[str, list[float]], baseline: dict[str, bool]) -> pd.DataFrame:
    rows = []
    for planner, values in flows.items():
        for k, flow in enumerate(values):
            rows.append(
                {
                    "planner": planner,
                    "scenario": f"scenario_{k:03d}.json",
                    "flow_rate": flow,
                    "delay_mean": 10.0 - 10 * flow,
                    "stop_ratio_all": 0.5,
                    "baseline": baseline[planner],
                }
            )
    return pd.DataFrame(rows)


def test_strongest_baseline_is_the_non_learned_planner_with_the_highest_median_flow():
    flows = {"PR": [0.2, 0.3, 0.25], "AIM": [0.5, 0.1, 0.4], "RL:coop": [0.9, 0.9, 0.9]}
    runs = _runs(flows, {"PR": True, "AIM": True, "RL:coop": False})
    assert strongest_baseline(runs) == "AIM"  # median 0.4 > 0.25; the learned planner is not a candidate
    assert strongest_baseline(runs.assign(baseline=False)) is None
    assert strongest_baseline(runs.drop(columns="baseline")) is None


def test_paired_differences_and_their_interval():
    rng = np.random.default_rng(1)
    base = rng.uniform(0.2, 0.4, 30)
    gain = rng.normal(0.1, 0.05, 30)
    runs = _runs({"FIFO": list(base), "RL:coop": list(base + gain)}, {"FIFO": True, "RL:coop": False})
    paired = paired_differences(runs)
    assert tuple(paired.columns) == PAIRED_COLUMNS
    assert list(paired["metric"]) == ["flow_rate", "delay_mean", "stop_ratio_all"]
    assert (paired["baseline"] == "FIFO").all() and (paired["planner"] == "RL:coop").all()
    flow = paired.set_index("metric").loc["flow_rate"]
    assert flow["pairs"] == 30 and flow["mean_difference"] == pytest.approx(gain.mean())
    assert flow["ci_low"] < gain.mean() < flow["ci_high"]
    assert flow["ci_high"] - flow["ci_low"] < 4 * gain.std() / np.sqrt(30)  # about 2 x 1.96 standard errors
    delay = paired.set_index("metric").loc["delay_mean"]
    assert delay["mean_difference"] == pytest.approx(-10 * gain.mean())
    stops = paired.set_index("metric").loc["stop_ratio_all"]
    assert stops["ci_low"] == stops["ci_high"] == 0.0  # no difference on any scenario
    pd.testing.assert_frame_equal(paired, paired_differences(runs))  # seeded: the report repeats
    assert paired_differences(runs.assign(baseline=False)).empty


def test_bootstrap_interval_is_vectorized_over_columns():
    d = np.column_stack([np.arange(10.0), np.full(10, 2.0)])
    bounds = bootstrap_interval(d, np.random.default_rng(0), reps=2000)
    assert bounds.shape == (2, 2)
    assert bounds[0, 0] < 4.5 < bounds[1, 0] and (bounds[:, 1] == 2.0).all()


def test_a_flow_tie_goes_to_the_baseline_with_less_delay():
    runs = _runs({"PR": [0.3, 0.3], "FIFO": [0.3, 0.3]}, {"PR": True, "FIFO": True})
    runs.loc[runs["planner"] == "FIFO", "delay_mean"] = 1.0  # PR: 7 s
    assert strongest_baseline(runs) == "FIFO"
    assert strongest_baseline(runs.assign(delay_mean=np.nan)) == "PR"  # no delay known: the first listed


def test_the_paired_interval_is_the_plain_percentile_bootstrap_bit_for_bit():
    # The reports' figures stay as they were when comparison.py had its own bootstrap: the shared
    # one (sb3_graph.aggregate) gives the same bounds, bit for bit, as that code written out here.
    from envs.evaluation.comparison import CONFIDENCE, RESAMPLES

    d = np.random.default_rng(5).normal(size=(37, 3))
    index = np.random.default_rng(0).integers(0, 37, (RESAMPLES, 37))
    tail = 100 * (1 - CONFIDENCE) / 2
    expected = np.percentile(d[index].mean(axis=1), [tail, 100 - tail], axis=0)
    np.testing.assert_array_equal(bootstrap_interval(d, np.random.default_rng(0), RESAMPLES, CONFIDENCE), expected)


def test_a_shielded_baseline_is_a_baseline_and_a_shielded_model_is_not():
    """Full throttle behind the shield is non-learned: the report pairs the planners against it
    when it moves the most traffic."""
    from envs.evaluation.harness import is_baseline

    assert is_baseline("fullthrottle+shield") and is_baseline("AIM+shield") and is_baseline("pr")
    assert not is_baseline("envs/pretrained/coop_4way_residual/best_model.safetensors+shield")
    assert not is_baseline("envs/planners/adversarial.py:FullThrottle+shield")  # a user class: not built in
