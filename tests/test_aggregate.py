"""IQM and stratified bootstrap intervals over seeds and scenarios (sb3_graph.aggregate, sb3-graph aggregate)."""

import numpy as np
import pandas as pd
import pytest

from sb3_graph.aggregate import aggregate, iqm, stratified_bootstrap_ci
from sb3_graph.cli import main

# runs (seeds) x tasks (scenarios), by hand
HAND = np.array([[0.0, 10.0], [1.0, 20.0]])


def test_iqm_of_hand_made_numbers():
    assert iqm(np.arange(8.0)) == 3.5  # the middle half: 2, 3, 4, 5
    assert iqm(HAND) == 5.5  # pooled 0, 1, 10, 20: the middle two, 1 and 10
    assert iqm([4.0]) == 4.0
    assert iqm([1.0, 2.0, 3.0, 100.0, -100.0]) == 2.0  # int(0.25 * 5) = 1 cut at each end
    np.testing.assert_allclose(iqm(np.array([[1.0, 2, 3, 4], [5, 6, 7, 80]]), axis=1), [2.5, 6.5])


def test_iqm_equals_scipy_and_rliable_trimming():
    scores = np.random.default_rng(3).normal(size=(5, 7))
    stats = pytest.importorskip("scipy.stats")
    assert iqm(scores) == pytest.approx(stats.trim_mean(scores, 0.25, axis=None))
    try:
        from rliable import metrics
    except Exception:  # rliable is optional; its import may fail on a broken dependency
        pytest.skip("rliable.metrics is not importable")
    assert iqm(scores) == pytest.approx(metrics.aggregate_iqm(scores))


def test_interval_bounds_of_hand_made_numbers():
    # Each task's two runs resampled with replacement: 16 equally likely resamples. The lowest IQM
    # (both tasks draw their lower run: 0, 0, 10, 10 -> 5) and the highest (1, 1, 20, 20 -> 10.5)
    # each have probability 1/16 > 2.5 %, so they are the 95 % interval's bounds.
    assert stratified_bootstrap_ci(HAND, iqm, reps=5000) == (5.0, 10.5)
    # Stratified: tasks that are constant within themselves leave nothing to resample, however
    # different they are (a bootstrap of the pooled runs would mix them and give a wide interval).
    assert stratified_bootstrap_ci([[1.0, 1.0, 1.0], [5.0, 5.0, 5.0]], iqm) == (3.0, 3.0)
    assert stratified_bootstrap_ci([[1.0, 1.0, 1.0], [5.0, 5.0, 5.0]], np.mean) == (3.0, 3.0)
    # ragged tasks and the same seed give the same interval
    ragged = [[0.1, 0.5, 0.9], [2.0, 3.0]]
    assert stratified_bootstrap_ci(ragged, seed=1) == stratified_bootstrap_ci(ragged, seed=1)
    with pytest.raises(ValueError, match="confidence"):
        stratified_bootstrap_ci(HAND, confidence=1.0)
    with pytest.raises(ValueError, match="at least one run"):
        stratified_bootstrap_ci([[1.0], []])


def test_interval_matches_rliable_when_it_is_importable():
    try:
        from rliable import library, metrics
    except Exception:  # needs arch < 8, which breaks with pandas 3: checked where it imports
        pytest.skip("rliable.library is not importable")
    scores = np.random.default_rng(0).gamma(2.0, size=(5, 4))  # 5 seeds x 4 scenarios
    _, intervals = library.get_interval_estimates(
        {"x": scores}, lambda s: np.array([metrics.aggregate_iqm(s)]), reps=20000
    )
    low, high = stratified_bootstrap_ci(scores, iqm, reps=20000)
    np.testing.assert_allclose([low, high], intervals["x"][:, 0], atol=0.02 * float(np.ptp(scores)))


def test_aggregate_table_per_configuration_over_seeds_and_tasks():
    rows = [{"config": "a", "scenario": t, "seed": s, "flow": HAND[s, t], "delay": 1.0} for s in (0, 1) for t in (0, 1)]
    rows += [{"config": "b", "scenario": t, "seed": 0, "flow": 7.0, "delay": np.nan} for t in (0, 1)]
    table = aggregate(pd.DataFrame(rows), "config", "scenario", ["flow", "delay"], reps=5000, seed_column="seed")
    a = table[(table.config == "a") & (table.metric == "flow")].iloc[0]
    assert (a.iqm, a.ci_low, a.ci_high, a.runs, a.tasks, a.seeds) == (5.5, 5.0, 10.5, 4, 2, 2)
    assert a["mean"] == pytest.approx(7.75) and a["median"] == 5.5
    b = table[(table.config == "b") & (table.metric == "delay")].iloc[0]
    assert b.runs == 0 and np.isnan(b.iqm)  # undefined everywhere: no figure rather than a made-up one
    # the iid bootstrap also resamples across tasks: wider than the stratified one here
    iid = aggregate(pd.DataFrame(rows), "config", "scenario", ["flow"], reps=5000, stratified=False).iloc[0]
    assert iid.iqm == 5.5 and iid.ci_low < 5.0 and iid.ci_high > 10.5
    with pytest.raises(KeyError, match="missing"):
        aggregate(pd.DataFrame(rows), "config", "scenario", ["speed"])


def _report(folder, planners):
    folder.mkdir()
    rows = []
    for name, values in planners.items():
        for task, value in enumerate(values):
            rows.append({"planner": name, "run": task, "scenario": f"scenario_{task:03d}.json", "flow_rate": value,
                         "stop_ratio_all": 0.1, "delay_mean": 2.0, "collision_rate": 0.0})  # fmt: skip
    pd.DataFrame(rows).to_csv(folder / "metrics.csv", index=False)
    return folder


def test_aggregate_command_pools_seeds_into_one_configuration(tmp_path, capsys):
    table1 = _report(tmp_path / "table1", {"PR": [0.3, 0.3], "RL:seed_0": [0.0, 10.0], "RL:seed_1": [1.0, 20.0]})
    tuned = _report(tmp_path / "tuned", {"RL:seed_0": [0.5, 0.5]})
    out = tmp_path / "agg"
    assert main(["aggregate", str(table1), f"best={tuned}", "--out", str(out), "--reps", "5000"]) == 0
    table = pd.read_csv(out / "aggregate.csv")
    flow = table[table.metric == "flow_rate"].set_index("configuration")
    assert sorted(flow.index) == ["best:RL:seed_*", "table1:PR", "table1:RL:seed_*"]
    rl = flow.loc["table1:RL:seed_*"]
    assert (rl.iqm, rl.ci_low, rl.ci_high, rl.runs, rl.seeds, rl.tasks) == (5.5, 5.0, 10.5, 4, 2, 2)
    assert flow.loc["table1:PR"].seeds == 0  # a baseline has no training seed
    assert "| table1:RL:seed_* | flow_rate | 5.5 [5, 10.5] |" in (out / "aggregate.md").read_text()
    assert len(pd.read_csv(out / "runs.csv")) == 8
    # one run per scenario (a baseline): a point under the stratified bootstrap, an interval under iid
    pr = _report(tmp_path / "pr", {"PR": [0.1, 0.2, 0.3, 0.4]})
    assert main(["aggregate", str(pr), "--out", str(tmp_path / "pr_s")]) == 0
    assert main(["aggregate", str(pr), "--bootstrap", "iid", "--out", str(tmp_path / "pr_i")]) == 0
    point = pd.read_csv(tmp_path / "pr_s" / "aggregate.csv").iloc[0]
    spread = pd.read_csv(tmp_path / "pr_i" / "aggregate.csv").iloc[0]
    assert point.ci_low == point.ci_high == point.iqm == pytest.approx(0.25)
    assert spread.ci_low < 0.25 < spread.ci_high
    capsys.readouterr()
    # bad input: one line naming the flag; an existing output is never overwritten
    for extra, message in [
        (["--out", str(out)], "exists"),
        (["--metrics", "speed"], "no column ['speed']; --metrics allowed:"),
        (["--seed-pattern", "seed_\\d+"], "--seed-pattern"),
        (["--confidence", "95"], "--confidence must be in (0, 1)"),
        (["--bootstrap", "block"], "--bootstrap must be stratified or iid"),
    ]:
        args = ["aggregate", str(table1), "--out", str(tmp_path / "new"), *extra]
        assert main(args) == 2
        assert message in capsys.readouterr().err
    assert main(["aggregate", str(table1), str(table1 / "metrics.csv"), "--out", str(tmp_path / "x")]) == 2
    assert "given twice" in capsys.readouterr().err
    assert main(["aggregate", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2
    assert "no metrics.csv" in capsys.readouterr().err
