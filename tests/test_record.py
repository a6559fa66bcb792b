"""``sb3-graph record``: one frame per policy step, on every layout, headless; bad input is one line."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from envs.simulation.layouts import LAYOUT_NAMES
from envs.simulation.rendering import COLLIDED, MOVING, STOPPED, EpisodeRecorder, outlines
from envs.simulation.step_record import StepRecord
from sb3_graph.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV_OF_LAYOUT = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}
FAST = ["--dpi", "20", "--no-progress"]


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_record_writes_one_gif_frame_per_policy_step(layout, tmp_path, capsys):
    out = tmp_path / "episode.gif"
    duration = 2.4
    rc = main(["record", "--env", ENV_OF_LAYOUT[layout], "--planner", "fifo", "--seed", "1",
               "--duration", str(duration), "--out", str(out), *FAST])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    with Image.open(out) as gif:
        assert gif.n_frames == round(duration * 5)  # the 5 Hz policy: 12 steps
    assert not list(tmp_path.glob(".*"))  # no partial file left beside it


def test_record_html_is_self_contained_and_a_still_is_written(tmp_path, capsys):
    out, still = tmp_path / "episode.html", tmp_path / "frame.png"
    assert main(["record", "--planner", "lead=aim", "--planner", "fifo+shield", "--duration", "1", "--out", str(out),
                 "--still", str(still), *FAST]) == 0  # fmt: skip
    assert [line.split(":")[0].strip() for line in capsys.readouterr().out.splitlines()[:2]] == ["lead", "FIFO+shield"]
    html = out.read_text()
    assert html.count("data:image/png;base64") == 5 and "<script" in html  # frames embedded, no side files
    assert "http://" not in html and "https://" not in html and "<link" not in html  # loads nothing (no CDN)
    assert html.count("<button") == 9 and 'class="fa' not in html  # the player's buttons, as Unicode glyphs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode.html", "frame.png"]
    with Image.open(still) as image:
        assert image.size[0] > image.size[1] > 100  # two panels side by side


def test_record_mp4(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / "episode.mp4"
    assert main(["record", "--planner", "pr", "--duration", "1", "--out", str(out), *FAST]) == 0
    assert out.stat().st_size > 1000 and out.read_bytes()[4:8] == b"ftyp"


def test_record_headless_prints_no_display_error(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "XDG_RUNTIME_DIR", "WAYLAND_DISPLAY")}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    result = subprocess.run(
        [sys.executable, "-m", "sb3_graph.cli", "record", "--planner", "fifo", "--duration", "0.6",
         "--out", str(tmp_path / "e.gif"), *FAST],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "XDG_RUNTIME_DIR" not in result.stderr and "error" not in result.stderr.lower()
    assert "3 frames" in result.stdout


def test_record_replays_a_run_of_an_evaluate_report(tmp_path, capsys):
    report = tmp_path / "report"
    assert main(["evaluate", "--planner", "fifo", "--scenarios", "2", "--duration", "6", "--seed", "4", "--jobs", "1",
                 "--out", str(report), "--no-progress"]) == 0  # fmt: skip
    assert json.loads((report / "run.json").read_text())["replay"]["seed"] == 4
    capsys.readouterr()
    out = tmp_path / "run1.gif"
    assert main(["record", "--report", str(report), "--run", "1", "--out", str(out), *FAST]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "FIFO" in line and "(report, run 1:" in line and "differs" not in line, line
    with Image.open(out) as gif:
        assert gif.n_frames == 30
    late = tmp_path / "late.gif"
    assert main(["record", "--report", str(report), "--run", "1", "--from", "4", "--out", str(late), *FAST]) == 0
    with Image.open(late) as gif:
        assert gif.n_frames == 10  # 4 s to 6 s
    # a report written before run.json kept the replay settings: read from report.md's settings list
    info = json.loads((report / "run.json").read_text())
    del info["replay"]
    (report / "run.json").write_text(json.dumps(info))
    capsys.readouterr()
    old = tmp_path / "old.gif"
    assert main(["record", "--report", str(report), "--run", "1", "--from", "5", "--out", str(old), *FAST]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "FIFO" in line and "(report, run 1:" in line and "differs" not in line, line


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--out", "x.avi", "--planner", "fifo"], "--out: must end in .gif, .mp4, .html"),
        (["--out", "x.gif", "--planner", "nobody"], "--planner"),
        (["--out", "x.gif", "--planner", "fifo", "--run", "3"], "--run needs --report"),
        (["--out", "x.gif", "--report", "nowhere", "--run", "0"], "--report: 'nowhere' is not an evaluate report"),
        (["--out", "x.gif", "--planner", "a b=fifo"], "--planner: label 'a b' in 'a b=fifo' is not a valid label"),
        (["--out", "x.gif", "--planner", "x=fifo", "--planner", "x=aim"], "both get the label 'x'"),
        (["--out", "x.gif", "--planner", "fifo", "--duration", "-1"], "--duration must be positive"),
        (["--out", "x.gif", "--planner", "fifo", "--duration", "5", "--from", "5"], "--from must be in [0, 5)"),
        (["--out", "x.gif", "--planner", "fifo", "--scenario", "missing.json"], "file not found: 'missing.json'"),
    ],
)
def test_bad_input_is_one_line(extra, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["record", *extra, *FAST]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not list(tmp_path.iterdir())


def test_record_defaults_to_the_shipped_planner_behind_the_shield(tmp_path, capsys):
    from envs.commands.evaluate import DEFAULT_MODEL
    from envs.planners import planner_name

    out = tmp_path / "episode.gif"
    assert main(["record", "--duration", "0.6", "--out", str(out), *FAST]) == 0
    name = planner_name(str(DEFAULT_MODEL) + "+shield")
    assert capsys.readouterr().out.splitlines()[0].strip().startswith(f"{name}:")


def test_existing_out_is_refused(tmp_path, capsys):
    out = tmp_path / "mine.gif"
    out.write_bytes(b"mine")
    assert main(["record", "--planner", "fifo", "--out", str(out), *FAST]) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == b"mine"


class _Scene:
    def __init__(self, ids, speed, time=0.0):
        n = len(ids)
        self.vehicle_id, self.speed, self.time = np.asarray(ids), np.asarray(speed, float), time
        self.position, self.heading = np.zeros((n, 2)), np.zeros(n)
        self.length, self.width = np.full(n, 4.0), np.full(n, 2.0)

    @property
    def num_vehicles(self):
        return len(self.vehicle_id)


def test_recorder_states_and_collided_vehicles_stay_drawn():
    class Shielded:
        last_overridden = np.array([False, True, False, False])

    recorder = EpisodeRecorder(Shielded())
    before = _Scene([1, 2, 3, 4], [5.0, 5.0, 0.0, 3.0])
    after = _Scene([1, 2], [5.0, 5.0])  # 3 and 4 collided and were removed
    recorder(before, np.zeros(4), StepRecord(time=0.2, collisions=[[3, 4]]), after)
    frame = recorder.frames[-1]
    assert list(frame.state) == [MOVING, 3, COLLIDED, COLLIDED] and frame.collided == 2 and frame.in_scene == 2
    recorder.planner = object()
    still = _Scene([1, 2], [0.1, 5.0])
    recorder(after, np.zeros(2), StepRecord(time=0.4, governed=[2], crossed=[1]), still)
    assert list(recorder.frames[-1].state) == [STOPPED, 2, COLLIDED, COLLIDED] and recorder.frames[-1].crossed == 1
    recorder(still, np.zeros(2), StepRecord(time=2.4), still)  # 2 s after: the wrecks are gone
    assert len(recorder.frames[-1].state) == 2


def test_outlines():
    corners = outlines(np.array([[10.0, 0.0]]), np.array([np.pi / 2]), np.array([4.0]), np.array([2.0]))
    assert np.allclose(corners[0], [[9, 2], [9, -2], [11, -2], [11, 2]])  # front left first, counter-clockwise


def test_drive_a_planner_example_runs_the_harness_loop():
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    result = subprocess.run(
        [sys.executable, "examples/drive_a_planner.py", "--planner", "fifo", "--seed", "3", "--duration", "12"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("fifo: ") and "collided in 12.0 s" in result.stdout
