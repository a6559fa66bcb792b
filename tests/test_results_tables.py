"""scripts/results_tables.py: the README's results table and the results page come from one summary file."""

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "results_tables.py"
spec = importlib.util.spec_from_file_location("results_tables", SCRIPT)
results_tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(results_tables)


def _block(text: str, name: str) -> str:
    found = re.search(rf"<!-- results:{name} -->\n(.*?)<!-- /results:{name} -->", text, re.DOTALL)
    assert found, name
    return found.group(1)


def test_readme_and_results_page_are_what_the_generator_writes(capsys):
    # A hand edit of a table (or a new summary file without rerunning the script) fails here.
    assert results_tables.main(["--check"]) == 0, capsys.readouterr().out


def test_readme_and_results_page_show_the_same_table():
    readme = (ROOT / "README.md").read_text()
    page = (ROOT / "docs" / "results.md").read_text()
    for name in ("main-summary", "main-table"):
        assert _block(readme, name) == _block(page, name) != ""
    data = json.loads(results_tables.DATA.read_text())
    table = _block(readme, "main-table")
    for name, planner in data["planners"].items():  # every planner of the summary file, with its median flow
        label = results_tables.LABELS.get(name, name)
        (row,) = [line for line in table.splitlines() if line.startswith(f"| {label} |")]
        assert f"{planner['flow_median']:.3f}" in row


def test_an_edited_table_is_found_out():
    data = json.loads(results_tables.DATA.read_text())
    names = results_tables.PAGES[ROOT / "README.md"]
    text = (ROOT / "README.md").read_text()
    assert results_tables.render_page(text, data, names) == text
    edited = text.replace("| FIFO | ", "| FIFO | 0.999 ", 1)
    assert edited != text and results_tables.render_page(edited, data, names) == text
    with pytest.raises(ValueError, match="README.md: no '<!-- results:main-summary -->'"):
        results_tables.render_page("no markers", data, names, "README.md")


def test_a_report_is_read_into_the_summary_file(tmp_path):
    # A small report written by the report code itself: what --report reads after a new main job.
    from envs.evaluation.metrics import run_metrics
    from envs.evaluation.report import write_report

    runs, vehicles = [], []
    for planner, stopped in (("Glide+shield", 0.2), ("RL:coop_4way_advice+shield", 0.1)):
        for k in range(4):
            n = 40
            frame = pd.DataFrame({
                "vehicle_id": np.arange(n), "route": "r", "priority": "major", "maneuver": "straight",
                "first_seen": 0.0, "path_length": 100.0, "speed_limit": 10.0, "crossed": 10.0 + k, "removed": np.nan,
                "stopped": np.arange(n) < stopped * n * (1 + k / 10), "collided": False,
            })  # fmt: skip
            row = {"planner": planner, "run": k, "scenario": f"scenario_{k:03d}.json", "baseline": "Glide" in planner}
            row.update(run_metrics(frame, 100.0))
            runs.append(row)
            vehicles.append(frame.assign(planner=planner, scenario=row["scenario"]))
    report = tmp_path / "report"
    report.mkdir()
    write_report(report, pd.DataFrame(runs), pd.concat(vehicles, ignore_index=True), {"environment": "stub"})
    replay = {"env": "CoopIntersection4Way-v0", "seed": 0, "duration": 100.0}
    (report / "run.json").write_text(json.dumps({"replay": replay}))
    data = results_tables.read_report(report)
    summary = json.loads((report / "summary.json").read_text())
    assert list(data["planners"]) == list(summary)
    advice = data["planners"]["RL:coop_4way_advice+shield"]
    assert advice["stops"]["all"] == pytest.approx(summary["RL:coop_4way_advice+shield"]["stop_ratio"]["all"])
    assert {r["metric"] for r in data["paired"]} >= {"flow_rate", "delay_mean", "stop_ratio_all"}
    assert data["scenarios"] == 4 and data["vehicles"] == 40 * 4
    lines = results_tables.summary_text(data)
    assert lines[-1].startswith("**In short:** The GNN advice policy + shield has fewer stopped vehicles than glide")
    table = results_tables.main_table(data)
    assert table[2].startswith("| glide (arrival times) + shield |") and len(table) == 2 + 2 + 2
