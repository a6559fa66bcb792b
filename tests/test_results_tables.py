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


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """A small evaluate report written by the report code itself: what --report reads after a new main job."""
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
    folder = tmp_path_factory.mktemp("report")
    write_report(folder, pd.DataFrame(runs), pd.concat(vehicles, ignore_index=True), {"environment": "stub"})
    replay = {"env": "CoopIntersection4Way-v0", "seed": 0, "duration": 100.0}
    (folder / "run.json").write_text(json.dumps({"replay": replay}))
    return folder


def test_a_report_is_read_into_the_summary_file(report):
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


def test_one_command_rewrites_both_pages_from_a_new_report(report, tmp_path, monkeypatch):
    # What the main job's rerun takes: `python scripts/results_tables.py --report DIR`, on copies of the pages.
    pages = {}
    for page, names in results_tables.PAGES.items():
        copy = tmp_path / page.name
        copy.write_text(page.read_text())
        pages[copy] = names
    monkeypatch.setattr(results_tables, "PAGES", pages)
    monkeypatch.setattr(results_tables, "ROOT", tmp_path)
    monkeypatch.setattr(results_tables, "FIGURES_DIR", tmp_path / "figures" / "main")
    data = tmp_path / "main.json"
    assert results_tables.main(["--report", str(report), "--data", str(data)]) == 0
    assert results_tables.main(["--check", "--data", str(data)]) == 0
    readme, page = (tmp_path / "README.md").read_text(), (tmp_path / "results.md").read_text()
    assert _block(readme, "main-table") == _block(page, "main-table")
    assert "| FIFO |" not in _block(readme, "main-table")  # the old planners are gone, the report's are there
    assert "| GNN advice policy (shipped) + shield |" in _block(readme, "main-table")
    assert (tmp_path / "figures" / "main" / "flow_rate.png").is_file()
    assert "![flow rate](figures/main/flow_rate.png)" in _block(page, "main-figures")
