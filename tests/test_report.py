"""The evaluation report: collided vehicles as counts (a rounded rate hides them), readable figures."""

import json

import matplotlib.image
import numpy as np
import pandas as pd

from envs.evaluation.metrics import run_metrics
from envs.evaluation.report import FIGURES, collided_text, write_report


def _results(collided_in_fifo: int, extra: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    runs, vehicles = [], []
    names = ("PR", "FIFO", "RL:coop_4way_fair", "RL:coop_4way_fair+shield", *(f"planner_{k}" for k in range(extra)))
    for planner in names:
        for k in range(2):
            n = 500  # 2 of 1,000 vehicles: 0.2 %, "0.0 %" once rounded to a tenth of a percent of 10 %
            collided = np.zeros(n, bool)
            if planner == "FIFO" and k == 0:
                collided[:collided_in_fifo] = True
            frame = pd.DataFrame(
                {
                    "vehicle_id": np.arange(n), "route": "r", "priority": "major", "maneuver": "straight",
                    "first_seen": 0.0, "path_length": 100.0, "speed_limit": 10.0,
                    "crossed": np.where(collided, np.nan, 10.0), "removed": np.nan, "stopped": False,
                    "collided": collided,
                }
            )  # fmt: skip
            row = {"planner": planner, "run": k, "scenario": f"scenario_{k:03d}.json"}
            row.update(run_metrics(frame, 100.0))
            runs.append(row)
            vehicles.append(frame.assign(planner=planner, scenario=row["scenario"]))
    return pd.DataFrame(runs), pd.concat(vehicles, ignore_index=True)


def test_collided_vehicles_are_integer_counts_in_summary_and_report(tmp_path):
    runs, vehicles = _results(collided_in_fifo=2)
    write_report(tmp_path, runs, vehicles, {"environment": "stub"})
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["FIFO"]["collided"] == 2 and isinstance(summary["FIFO"]["collided"], int)
    assert summary["PR"]["collided"] == 0
    report = (tmp_path / "report.md").read_text()
    assert "| 2 / 1000 (0.2 %) |" in report and "| 0 / 1000 (0 %) |" in report


def test_collided_text():
    assert collided_text(2, 9183) == "2 / 9183 (0.022 %)"
    assert collided_text(431, 9183) == "431 / 9183 (4.7 %)"
    assert collided_text(None, 10) == "n/a"


def test_figures_are_written_with_the_offered_flow_and_delay(tmp_path):
    runs, vehicles = _results(collided_in_fifo=3)
    write_report(tmp_path, runs, vehicles, {"environment": "stub"})
    assert "delay_collisions.png" in FIGURES
    for figure in FIGURES:
        image = matplotlib.image.imread(tmp_path / figure)
        assert image.shape[0] > 100 and image.shape[1] > 100


def _drawn(monkeypatch, draw) -> list:
    """The figures that ``draw()`` makes (kept open: the report closes them after saving)."""
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    draw()
    return figures


def test_figures_have_titles_and_a_log_axis_where_one_bar_dwarfs_the_others(tmp_path, monkeypatch):
    from envs.evaluation.report import delay_collision_figure, dwarfed, flow_rate_figure, stop_figure

    assert dwarfed([5229, 2, 0]) and not dwarfed([30, 2, 0]) and not dwarfed([5229, 0]) and not dwarfed([])
    runs, vehicles = _results(collided_in_fifo=2)
    planners = list(pd.unique(runs["planner"]))
    for counts, scale in (({"PR": 2600}, "symlog"), ({"PR": 10}, "linear")):  # PR 2 x 2600 beside FIFO's 2
        mine = runs.assign(collided=runs["planner"].map(counts).fillna(runs["collided"]))
        (fig,) = _drawn(monkeypatch, lambda mine=mine: delay_collision_figure(mine, planners, tmp_path / "d.png"))
        left, right = fig.axes
        assert "delay" in left.get_title().lower() and "collided" in right.get_title().lower()
        assert right.get_yscale() == scale
    (fig,) = _drawn(monkeypatch, lambda: flow_rate_figure(runs, planners, tmp_path / "f.png"))
    assert fig.axes[0].get_title().startswith("Flow rate")
    (fig,) = _drawn(monkeypatch, lambda: stop_figure(vehicles, planners, "maneuver", ["straight"], tmp_path / "s.png"))
    legend = fig.axes[0].get_legend()
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels == [*planners, "vehicles (light)", "stopped (dark)"]  # one entry per planner, not two
    assert min(text.get_fontsize() for text in legend.get_texts()) >= 9


def test_figures_are_at_most_two_and_a_half_times_as_wide_as_high_with_many_planners(tmp_path):
    for extra in (0, 4, 8):  # 4, 8 and 12 planners
        out = tmp_path / str(extra)
        out.mkdir()
        runs, vehicles = _results(collided_in_fifo=1, extra=extra)
        write_report(out, runs, vehicles, {"environment": "stub"})
        for figure in FIGURES:
            height, width = matplotlib.image.imread(out / figure).shape[:2]
            assert width / height <= 2.5, (extra, figure, width, height)


def test_no_planner_is_drawn_in_a_key_swatch_colour():
    from matplotlib import colors as mcolors

    from envs.evaluation.report import KEY_COLORS, planner_colors

    colors = planner_colors(20)
    assert len(set(colors[:18])) == 18  # 18 distinct colours before they repeat
    for color in colors:
        r, g, b = mcolors.to_rgb(color)
        assert len({round(r, 2), round(g, 2), round(b, 2)}) > 1, color  # not grey, not black
        assert color not in {mcolors.to_hex(key) for key in KEY_COLORS}


def test_report_units_one_per_quantity(tmp_path):
    runs, vehicles = _results(collided_in_fifo=2)
    write_report(tmp_path, runs, vehicles, {"environment": "stub"})
    report = (tmp_path / "report.md").read_text()
    assert "governor held back [% of vehicle-steps]" in report
    from envs.evaluation.comparison import PAIRED_COLUMNS
    from envs.evaluation.report import _paired_section

    paired = pd.DataFrame(
        [
            ("A", "PR", "stop_ratio_all", 10, -0.096, -0.12, -0.07),
            ("A", "PR", "energy_kj_per_vehicle", 10, 11.8, 7.6, 15.7),
        ],
        columns=list(PAIRED_COLUMNS),
    )
    table = _paired_section(paired)
    assert table[-3].endswith("| Δ stops [pp] | Δ energy [kJ per crossed vehicle] |")
    assert table[-1] == "| A | 10 | -9.6 [-12.0, -7.0] | +12 [+8, +16] |"  # points of a share; kJ, no decimals
    from envs.evaluation.report import _motion_table

    summary = {"A": {"slow_ratio": 0.506, "stop_ratio": {"all": 0.183}, "hard_brakes_per_vehicle": 0.86,
                     "energy_kj_per_vehicle": 103.4}}  # fmt: skip
    assert _motion_table(summary)[-1] == "| A | 50.6 % | 18.3 % | 0.86 | 103 |"  # percent; kJ with no decimals
