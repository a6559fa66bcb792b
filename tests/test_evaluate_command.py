"""``sb3-graph evaluate`` end to end on a small run, and its refusals."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from envs.evaluation.comparison import PAIRED_METRICS
from envs.evaluation.report import REPORT_FILES
from sb3_graph.cli import main

SUMMARY_KEYS = {
    "runs", "vehicles", "vehicles_scheduled", "not_spawned", "flow_rate", "offered_flow", "stop_ratio",
    "collision_rate", "collided", "delay_s", "speed_limit_violations", "governor_share", "stuck_runs",
    "last_crossing_s", "slow_ratio", "hard_brakes_per_vehicle", "energy_kj_per_vehicle",
}  # fmt: skip
SMALL = ["--scenarios", "2", "--duration", "20", "--seed", "3", "--jobs", "1", "--no-progress"]


def test_unknown_planner_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["evaluate", "--planner", "random", "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "random" in err and "pr, fifo" in err and ".zip" in err
    assert not out.exists()


def test_missing_model_file_is_a_clear_error(tmp_path, capsys):
    model = tmp_path / "nope.zip"
    assert main(["evaluate", "--planner", str(model), "--out", str(tmp_path / "r"), *SMALL]) == 2
    assert "nope.zip" in capsys.readouterr().err


def test_existing_out_is_refused_and_untouched(tmp_path, capsys):
    out = tmp_path / "report"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(["evaluate", "--planner", "pr", "--out", str(out), *SMALL]) == 2
    assert "exists" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["mine.txt"] and (out / "mine.txt").read_text() == "keep"


def test_bad_numbers_are_refused(tmp_path, capsys):
    for flag, value in (("--scenarios", "0"), ("--duration", "-1"), ("--jobs", "0")):
        args = ["evaluate", "--out", str(tmp_path / "r"), *SMALL, flag, value]
        assert main(args) == 2
        assert flag in capsys.readouterr().err


def test_small_run_writes_every_file_and_repeats(tmp_path):
    out = tmp_path / "report"
    assert main(["evaluate", "--planner", "pr", "--planner", "fifo", "--out", str(out), *SMALL]) == 0
    for name in REPORT_FILES:
        assert (out / name).is_file(), name
    scenarios = sorted((out / "scenarios").iterdir())
    assert len(scenarios) == 2
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary) == ["PR", "FIFO"]
    for entry in summary.values():
        assert set(entry) == SUMMARY_KEYS
        assert entry["runs"] == 2 and entry["vehicles"] > 0
        assert set(entry["flow_rate"]) == {"median", "q1", "q3", "mean"}
        assert set(entry["stop_ratio"]) == {"all", "major", "minor", "left", "straight", "right"}
        assert set(entry["delay_s"]) == {"median", "mean"}
        assert entry["collision_rate"] == 0.0
    # both planners are measured on the same scheduled vehicles, including any that never appeared
    assert summary["PR"]["vehicles_scheduled"] == summary["FIFO"]["vehicles_scheduled"]
    for entry in summary.values():
        assert entry["vehicles"] == entry["vehicles_scheduled"] >= entry["not_spawned"]
    metrics = pd.read_csv(out / "metrics.csv")
    assert len(metrics) == 4 and set(metrics["planner"]) == {"PR", "FIFO"}
    assert metrics["baseline"].all()
    paired = pd.read_csv(out / "paired.csv")  # the other baseline against the one with the higher median flow
    assert len(paired) == len(PAIRED_METRICS) and paired["pairs"].eq(2).all() and paired["planner"].nunique() == 1

    # Same scenario files, same seed: the same numbers (the run is deterministic), in a new folder.
    again = tmp_path / "again"
    args = ["evaluate", "--planner", "pr", "--planner", "fifo", "--out", str(again), *SMALL]
    assert main([*args, "--scenario-dir", str(out / "scenarios")]) == 0
    cols = ["planner", "scenario", "vehicles", "crossed", "stopped_all", "collided"]
    pd.testing.assert_frame_equal(pd.read_csv(again / "metrics.csv")[cols], metrics[cols])
    assert not (again / "scenarios").exists()


@pytest.mark.slow
def test_parallel_jobs_give_the_same_numbers(tmp_path):
    args = ["evaluate", "--planner", "pr", "--planner", "fifo", *SMALL]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--jobs", "2", "--out", str(tmp_path / "two")]) == 0
    one = pd.read_csv(tmp_path / "one" / "metrics.csv").drop(columns=["wall_s"])
    two = pd.read_csv(tmp_path / "two" / "metrics.csv").drop(columns=["wall_s"])
    pd.testing.assert_frame_equal(one, two)


def test_saved_model_runs_as_a_planner(tmp_path):
    """A saved (here untrained) sb3_graph TD3 model is a planner like the baselines."""
    import gymnasium as gym
    import torch

    import envs  # noqa: F401
    from sb3_graph import TD3, GraphPolicy

    torch.set_num_threads(1)
    model_path = tmp_path / "coop" / "best_model.zip"
    model_path.parent.mkdir()
    TD3(GraphPolicy, gym.make("CoopIntersection4Way-v0"), buffer_size=10, seed=0).save(model_path)
    out = tmp_path / "report"
    args = ["evaluate", "--planner", "fifo", "--planner", str(model_path), "--out", str(out)]
    assert main([*args, "--scenarios", "1", "--duration", "10", "--jobs", "1", "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary) == ["FIFO", "RL:coop"] and summary["RL:coop"]["runs"] == 1


def test_scenarios_of_another_layout_are_refused(tmp_path, capsys):
    from envs.simulation.traffic import generate_scenario

    folder = tmp_path / "scenarios"
    folder.mkdir()
    generate_scenario("3way", 10.0, 0).save(folder / "scenario_000.json")
    args = [
        "evaluate",
        "--planner",
        "pr",
        "--scenario-dir",
        str(folder),
        "--out",
        str(tmp_path / "r"),
        *SMALL,
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "scenario_000.json" in err and "3way" in err and "4way" in err
    assert not (tmp_path / "r").exists()
    assert main([*args[: -len(SMALL)], "--scenario-dir", str(tmp_path / "empty")]) == 2


def test_default_planners_are_the_baselines_and_the_shipped_model():
    from envs.commands.evaluate import DEFAULT_MODEL, checked_planners
    from sb3_graph.cli import UserError

    planners = checked_planners(None)
    expected = ["PR", "FIFO", "AIM", "SIGNAL", "FullThrottle+shield", "Glide+shield"]
    assert [name for _, name in planners][:6] == expected
    assert planners[6][0] == str(DEFAULT_MODEL)  # sb3-graph ind uses the same defaults
    assert planners[7] == (str(DEFAULT_MODEL) + "+shield", planners[6][1] + "+shield")  # and shielded
    assert [name for _, name in checked_planners(["pr"], shield=True)] == ["PR+shield"]
    assert [name for _, name in checked_planners(None, reserved=("inD",))] == [name for _, name in planners]
    with pytest.raises(UserError, match="given twice"):
        checked_planners(["fifo", "fifo"])
    with pytest.raises(UserError, match="reserved"):
        checked_planners(["fifo"], reserved=("FIFO",))


def test_report_states_the_simulated_duration_of_shorter_scenario_files(tmp_path):
    from envs.simulation.traffic import generate_scenario

    folder = tmp_path / "scenarios"
    folder.mkdir()
    generate_scenario("4way", 4.0, 0).save(folder / "scenario_000.json")
    out = tmp_path / "r"
    args = ["evaluate", "--planner", "pr", "--scenario-dir", str(folder), "--out", str(out), *SMALL]
    assert main(args) == 0  # SMALL asks for --duration 20
    report = (out / "report.md").read_text()
    assert "4 s (--duration 20 s; a run ends with its scenario file)" in report
    assert pd.read_csv(out / "metrics.csv")["duration_s"].tolist() == [pytest.approx(4.0)]
    assert not list(tmp_path.glob(".r.partial-*"))  # the staging folder became --out


def test_shipped_safetensors_and_zip_give_the_same_report(tmp_path):
    from envs.commands.evaluate import PAPER_MODEL

    copy = tmp_path / "zip" / "best_model.zip"
    copy.parent.mkdir()
    copy.write_bytes(PAPER_MODEL.with_suffix(".zip").read_bytes())
    args = ["evaluate", "--planner", str(PAPER_MODEL), "--planner", str(copy), "--out", str(tmp_path / "r")]
    assert main([*args, "--scenarios", "1", "--duration", "10", "--jobs", "1", "--no-progress"]) == 0
    runs = pd.read_csv(tmp_path / "r" / "metrics.csv").set_index("planner")
    cols = ["vehicles", "crossed", "stopped_all", "collided"]
    pd.testing.assert_series_equal(runs.loc["RL:coop_4way_fair", cols], runs.loc["RL:zip", cols], check_names=False)


def test_labels_are_report_names_and_tell_files_of_one_folder_name_apart(tmp_path, capsys):
    import shutil

    from envs.commands.evaluate import DEFAULT_MODEL

    files = []
    for run in ("default", "tuned"):  # .../<run>/seed_0/best_model.safetensors: both named after 'seed_0'
        (tmp_path / run / "seed_0").mkdir(parents=True)
        files.append(str(shutil.copy(DEFAULT_MODEL, tmp_path / run / "seed_0" / DEFAULT_MODEL.name)))
    unlabelled = ["evaluate", "--planner", files[0], "--planner", files[1], "--out", str(tmp_path / "x"), *SMALL]
    assert main(unlabelled) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "LABEL=SPEC" in err and "Traceback" not in err, err
    out = tmp_path / "r"
    args = ["evaluate", "--planner", "base=pr", "--planner", f"default={files[0]}", "--planner", f"tuned={files[1]}",
            "--shield", "--out", str(out), *SMALL]  # fmt: skip
    assert main(args) == 0
    last = capsys.readouterr().out.splitlines()[-6:]  # the command ends with the verdict, then the report's path
    assert last[0].startswith("In short: ")  # one sentence first
    assert last[1].startswith("Who leads, against base+shield (the strongest baseline)")
    assert [line.split(":")[0] for line in last[2:5]] == ["- flow", "- delay", "- stops"]
    assert last[5].startswith(f"report written to {out}")
    names = ["base+shield", "default+shield", "tuned+shield"]
    assert list(pd.unique(pd.read_csv(out / "metrics.csv")["planner"])) == names
    assert list(json.loads((out / "summary.json").read_text())) == names
    report = (out / "report.md").read_text()
    assert all(f"| {name} |" in report for name in names)
    assert report.splitlines()[2] == "## Verdict"  # report.md opens with the same verdict as the console
    assert [line.replace("**", "") for line in report.splitlines()[8:11]] == last[2:5]
    replay = json.loads((out / "run.json").read_text())["replay"]["planners"]
    assert [name for _, name in replay] == names and replay[1][0] == f"{files[0]}+shield"


@pytest.mark.parametrize(
    "words, message",
    [
        (["a=pr", "a=fifo"], "'a=fifo' and 'a=pr' both get the label 'a'"),
        (["FIFO=pr", "fifo"], "'fifo' and 'FIFO=pr' both get the report name 'FIFO'"),
        (["two words=pr"], "label 'two words' in 'two words=pr' is not a valid label"),
        (["empty="], "label 'empty' names no planner"),
        (["x=nobody"], "planner 'nobody' is unknown"),
    ],
)
def test_a_label_clash_or_a_bad_label_is_one_line(words, message, tmp_path, capsys):
    args = ["evaluate", *[f"--planner={w}" for w in words], "--out", str(tmp_path / "r"), *SMALL]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "r").exists()
