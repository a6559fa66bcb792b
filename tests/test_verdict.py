"""The verdict that opens every report: who leads on flow, delay and stops, by how much, and whether it is clear."""

from __future__ import annotations

import pandas as pd

from envs.evaluation.comparison import PAIRED_COLUMNS
from envs.evaluation.verdict import (
    HEADING,
    VERDICT_METRICS,
    VerdictMetric,
    compact_verdict,
    read_verdict,
    reference_comparison,
    verdict_lines,
)


def _paired(rows):
    return pd.DataFrame(rows, columns=list(PAIRED_COLUMNS))


def _line(lines, word):
    (line,) = [line for line in lines if line.startswith(f"- {word}:")]
    return line


def test_a_clear_winner_is_named_with_its_margin_and_interval():
    paired = _paired([
        ("GNN", "AIM", "flow_rate", 20, 0.052, 0.031, 0.070),
        ("GNN", "AIM", "delay_mean", 20, -1.25, -2.0, -0.5),
        ("GNN", "AIM", "stop_ratio_all", 20, 0.10, 0.05, 0.15),  # GNN stops more: AIM leads on stops
    ])  # fmt: skip
    lines = verdict_lines(paired, reference_means={"flow_rate": 0.4, "delay_mean": 5.0})
    assert lines[0] == HEADING and "against AIM (the strongest baseline)" in lines[4]
    assert lines[2] == (
        "**In short:** GNN has more flow than AIM (+0.052 veh/s); GNN has less delay than AIM (-1.25 s); AIM has "
        "fewer stopped vehicles than the closest, GNN (+10.0 percentage points for it)."
    )
    flow = _line(lines, "flow")
    assert flow.startswith("- flow: **GNN** leads by 0.052 veh/s (13.0 % of AIM's mean) over AIM")
    assert "GNN - AIM = +0.052 [+0.031, +0.070] veh/s over 20 scenarios" in flow
    assert flow.endswith("(its 95 % interval excludes zero)")
    delay = _line(lines, "delay")  # less delay is better: a negative difference is a lead
    assert delay.startswith("- delay: **GNN** leads by 1.25 s (25.0 % of AIM's mean) over AIM")
    assert "excludes zero" in delay
    stops = _line(lines, "stops")  # more stops is worse: the reference leads, in percentage points
    assert stops.startswith("- stops: **AIM** leads by 10.0 percentage points over GNN;")
    assert "[+5.0, +15.0] percentage points" in stops and "excludes zero" in stops


def test_an_interval_that_includes_zero_names_no_leader():
    paired = _paired([
        ("A", "PR", "flow_rate", 10, 0.004, -0.010, 0.018),
        ("A", "PR", "delay_mean", 10, 0.0, 0.0, 0.0),  # the same on every scenario
        ("A", "PR", "stop_ratio_all", 10, -0.02, -0.06, 0.01),
    ])  # fmt: skip
    lines = verdict_lines(paired)
    flow = _line(lines, "flow")
    assert flow == (
        "- flow: no clear lead; the best difference, A - PR = +0.004 [-0.010, +0.018] veh/s over 10 scenarios "
        "(its 95 % interval includes zero)"
    )
    assert _line(lines, "delay") == "- delay: tie, A and PR equal on all 10 paired scenarios"
    assert _line(lines, "stops").startswith("- stops: no clear lead;")
    for line in lines:  # a line that names a leader never also says that there is no clear lead
        assert not ("leads" in line and "no clear lead" in line), line
        assert "**" not in line.replace("**In short:**", "")
    assert lines[2] == "**In short:** No planner leads clearly on flow, delay or stops."


def test_the_best_of_several_planners_leads():
    paired = _paired([
        ("A", "PR", "flow_rate", 5, 0.01, 0.005, 0.02),
        ("B", "PR", "flow_rate", 5, 0.03, -0.01, 0.06),
        ("C", "PR", "flow_rate", 5, -0.02, -0.03, -0.01),
    ])  # fmt: skip
    # B has the best mean but an interval that includes zero: no leader is named
    assert _line(verdict_lines(paired), "flow").startswith("- flow: no clear lead; the best difference, B - PR")
    clear = paired.assign(ci_low=paired["ci_low"].clip(lower=0.001).where(paired["planner"] != "C", -0.03))
    assert _line(verdict_lines(clear), "flow").startswith("- flow: **B** leads by 0.030 veh/s over PR")
    worse = clear.assign(
        mean_difference=-clear["mean_difference"].abs() - 0.001, ci_low=-0.1, ci_high=-clear["ci_low"].abs()
    )
    line = _line(verdict_lines(worse), "flow")  # every planner clearly below the reference: the closest one is named
    assert line.startswith("- flow: **PR** leads by 0.011 veh/s over A (the closest)")


def test_only_the_metrics_it_is_told_enter_the_verdict():
    paired = _paired([
        ("A", "PR", "flow_rate", 5, 0.01, 0.005, 0.02),
        ("A", "PR", "energy_kj_per_vehicle", 5, -3.0, -4.0, -2.0),
    ])  # fmt: skip
    assert [line.split(":")[0] for line in verdict_lines(paired) if line.startswith("- ")] == ["- flow"]
    told = {**VERDICT_METRICS, "energy_kj_per_vehicle": VerdictMetric("energy", -1, "kJ/veh", 0)}
    assert _line(verdict_lines(paired, told), "energy").startswith("- energy: **A** leads by 3 kJ/veh over PR")


def test_without_a_baseline_the_first_planner_is_the_reference():
    runs = pd.DataFrame({
        "planner": ["default"] * 3 + ["tuned"] * 3, "scenario": ["s0", "s1", "s2"] * 2, "baseline": False,
        "flow_rate": [0.30, 0.32, 0.31, 0.35, 0.36, 0.37], "delay_mean": [4.0, 5.0, 4.5, 3.0, 3.5, 3.2],
        "stop_ratio_all": [0.2, 0.3, 0.25, 0.2, 0.3, 0.25],
    })  # fmt: skip
    table, kind = reference_comparison(runs, pd.DataFrame(columns=list(PAIRED_COLUMNS)))
    assert set(table["baseline"]) == {"default"} and "first planner" in kind
    lines = verdict_lines(table, reference_kind=kind)
    assert _line(lines, "flow").startswith("- flow: **tuned** leads by 0.050 veh/s over default")
    assert _line(lines, "stops") == "- stops: tie, tuned and default equal on all 3 paired scenarios"
    single, _ = reference_comparison(runs[runs["planner"] == "tuned"], table.iloc[:0])
    assert verdict_lines(single)[-1].startswith("No verdict: a single planner ran")


def test_report_opens_with_the_verdict_and_the_command_reads_it_back(tmp_path):
    from envs.evaluation.report import markdown_report

    paired = _paired([("A", "PR", "flow_rate", 4, 0.02, 0.01, 0.03)])
    verdict = verdict_lines(paired)
    text = markdown_report({}, pd.DataFrame(), pd.DataFrame({"planner": []}), {"seed": 0}, verdict=verdict)
    assert text.splitlines()[:3] == ["# Planner evaluation", "", HEADING]
    (tmp_path / "report.md").write_text(text)
    assert read_verdict(tmp_path) == [line for line in verdict[1:] if line]


def test_the_compact_verdict_names_only_clear_leaders():
    paired = _paired([
        ("A", "PR", "flow_rate", 5, 0.03, 0.01, 0.05),
        ("A", "PR", "delay_mean", 5, 0.5, -0.2, 1.0),  # A is slower, not clearly
        ("A", "PR", "stop_ratio_all", 5, 0.0, 0.0, 0.0),
    ])  # fmt: skip
    assert compact_verdict(paired) == "flow: A, delay: no clear lead, stops: tie"
    assert compact_verdict(paired.iloc[:0]) == "no verdict (a single planner)"


def test_a_planner_whose_vehicles_collided_cannot_lead_and_is_named():
    paired = _paired([
        ("Crasher", "Glide", "flow_rate", 10, 0.010, 0.002, 0.020),
        ("Crasher", "Glide", "delay_mean", 10, -3.0, -4.0, -2.0),
        ("Crasher", "Glide", "stop_ratio_all", 10, -0.40, -0.45, -0.35),
        ("Safe", "Glide", "flow_rate", 10, -0.003, -0.010, 0.005),
        ("Safe", "Glide", "delay_mean", 10, 0.35, 0.04, 0.64),
        ("Safe", "Glide", "stop_ratio_all", 10, -0.096, -0.12, -0.07),
    ])  # fmt: skip
    lines = verdict_lines(paired, collided={"Crasher": 2439, "Safe": 0, "Glide": 0})
    assert _line(lines, "stops").startswith("- stops: **Safe** leads by 9.6 percentage points over Glide")
    assert _line(lines, "flow").startswith("- flow: no clear lead; the best difference, Safe - Glide = -0.003")
    assert _line(lines, "delay").startswith("- delay: **Glide** leads by 0.35 s over Safe")
    assert lines[2].endswith("no planner leads clearly on flow; Crasher cannot lead, as its vehicles collided.")
    assert lines[-1] == "- not in the lead, as their vehicles collided: Crasher (2,439 vehicles)"
    assert "Crasher" not in "".join(lines[3:-1])  # named in the sentence and the last line only
    assert compact_verdict(paired, collided={"Crasher": 2439}) == (
        "flow: no clear lead, delay: Glide, stops: Safe, not in the lead (collided): Crasher"
    )
    alone = verdict_lines(paired[paired["planner"] == "Crasher"], collided={"Crasher": 5})  # no one else
    assert _line(alone, "flow").startswith("- flow: **Crasher** leads")
    assert alone[-1] == "- every planner compared with Glide collided: Crasher (5 vehicles)"
