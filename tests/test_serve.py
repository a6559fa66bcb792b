"""The planner server (``sb3-graph serve``) and its client: the same answers as in process, bad input
refused with the field named, one stream's state isolated from another's.

Most tests drive a real server process on an ephemeral loopback port (started once for the module,
with a token file and a small body limit); they skip when the ``serve`` extra (FastAPI, uvicorn) is
not installed. The wire mapping itself is checked without a server, on the recorded scenes of
``tests/data/planner_scenes.npz``.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
from serve_support import serve_process

import envs  # noqa: F401  (registers the environments)
from envs.planners import AIMPlanner, check_planner_spec, make_planner, planner_name
from envs.planners.shield import Shield
from envs.serve.client import DEADLINE_VARIABLE, TOKEN_FILE_VARIABLE, PlannerClient, RemotePlannerError
from envs.serve.wire import SceneBuilder, WireError, scene_to_wire
from envs.simulation.scene import Scene
from sb3_graph.cli import main

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "planner_scenes.npz"
FIELDS = (
    "vehicle_id", "route", "s", "position", "heading", "speed", "speed_limit", "dist_to_entry",
    "dist_to_exit", "leader", "gap", "priority", "maneuver", "length", "width", "arc",
)  # fmt: skip
ENV = "CoopIntersection4Way-v0"
MAX_BODY = 65536
TOKEN = "test-token-0123456789"


def _has_serve_extra() -> bool:
    try:
        import fastapi  # noqa: F401
        import msgspec  # noqa: F401
        import pydantic  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError:
        return False
    return True


SERVE_EXTRA = _has_serve_extra()
needs_server = pytest.mark.skipif(not SERVE_EXTRA, reason="the 'serve' extra (fastapi, uvicorn) is not installed")


def _bench():
    """``benchmarks/bench_serve.py``, where the malformed cases are listed (its table and this test share them)."""
    if "bench_serve" not in sys.modules:
        spec = importlib.util.spec_from_file_location("bench_serve", ROOT / "benchmarks" / "bench_serve.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules["bench_serve"] = module  # dataclasses look their module up by name
        spec.loader.exec_module(module)
    return sys.modules["bench_serve"]


# ---------------------------------------------------------------------- recorded scenes
@pytest.fixture(scope="module")
def recorded():
    with np.load(DATA) as data:
        return {key: data[key] for key in data.files}


_CONFIGS: dict[str, dict] = {}


def _config(env_id: str) -> dict:
    if env_id not in _CONFIGS:
        env = gym.make(env_id)
        _CONFIGS[env_id] = dict(env.unwrapped.config)
        env.close()
    return _CONFIGS[env_id]


def _scenes(data, run: str) -> list[Scene]:
    """The recorded scenes of a run, rebuilt (as tests/test_planner_regression.py does)."""
    builder = SceneBuilder(_config(str(data[f"{run}/env_id"])))
    lay = builder.layout
    counts = data[f"{run}/count"]
    ends = np.cumsum(counts)
    scenes = []
    for t, (start, end) in enumerate(zip(ends - counts, ends)):
        rows = slice(int(start), int(end))
        scenes.append(Scene(
            time=float(data[f"{run}/time"][t]), dt=float(data[f"{run}/dt"]), route_names=lay.route_names,
            conflicts=lay.conflicts, a_min=float(data[f"{run}/a_min"]), a_max=float(data[f"{run}/a_max"]),
            s_ref=float(data[f"{run}/s_ref"]), layout=lay, **{name: data[f"{run}/{name}"][rows] for name in FIELDS},
        ))  # fmt: skip
    return scenes


def _through_json(scene: Scene) -> dict:
    return json.loads(json.dumps(scene_to_wire(scene)))


@pytest.mark.parametrize("run", ["aim", "signal", "fullthrottle+shield_3way"])
def test_wire_rebuilds_recorded_scenes_bit_for_bit(recorded, run):
    """Scene -> JSON -> the server's scene: every array a planner reads is the recorded one, exactly."""
    builder = SceneBuilder(_config(str(recorded[f"{run}/env_id"])))
    busy = 0
    for scene in _scenes(recorded, run):
        wire = _through_json(scene)
        rebuilt = builder.scene(wire["layout"], wire["time"], [SimpleNamespace(**v) for v in wire["vehicles"]])
        busy += scene.num_vehicles > 1
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(rebuilt, name), getattr(scene, name), err_msg=f"{name} {scene.time}")
        settings = ("time", "dt", "a_min", "a_max", "s_ref")
        assert [getattr(rebuilt, k) for k in settings] == [getattr(scene, k) for k in settings]
        assert rebuilt.route_names == scene.route_names and rebuilt.layout is scene.layout
    assert busy > 10  # the runs hold scenes with leaders, gaps and conflicts, not only empty ones


def test_wire_refuses_what_the_intersection_cannot_hold(recorded):
    builder = SceneBuilder(_config(ENV))
    scene = next(s for s in _scenes(recorded, "aim") if s.num_vehicles >= 3)
    good = [SimpleNamespace(**v) for v in _through_json(scene)["vehicles"]]
    cases = {
        "layout": ("3way", good),
        "vehicles[1].route": ("4way", [good[0], SimpleNamespace(**{**vars(good[1]), "route": "south->moon"})]),
        "vehicles[1].id": ("4way", [good[0], SimpleNamespace(**{**vars(good[1]), "id": good[0].id})]),
        "vehicles[0].arc": ("4way", [SimpleNamespace(**{**vars(good[0]), "arc": 1e4})]),
        "vehicles[0].speed": ("4way", [SimpleNamespace(**{**vars(good[0]), "speed": 99.0})]),
        "vehicles": ("4way", good * 30),
    }
    for field, (layout, vehicles) in cases.items():
        with pytest.raises(WireError) as caught:
            builder.scene(layout, 0.0, vehicles)
        assert caught.value.field == field
    assert builder.scene("4way", 1.0, good).num_vehicles == len(good)  # the builder goes on


def test_the_benchmarks_pieces_of_a_step_run_on_the_current_schema():
    table = _bench().components(10, repeat=2)
    assert "PlannerService.handle" in table and table.count("\n| ") >= 8  # one row per piece, none failed


def test_the_benchmarks_queue_scene_stands_before_the_lines():
    scene, _ = _bench().queue_scene(48)
    assert scene.num_vehicles == 48 and (scene.speed == 0).all() and (scene.dist_to_entry > 0).all()
    with pytest.raises(ValueError, match="at most 48"):
        _bench().queue_scene(49)


def test_remote_spec_is_checked_without_a_server():
    assert check_planner_spec("http://127.0.0.1:8765") == "http://127.0.0.1:8765"
    assert check_planner_spec("http://localhost:8765/+shield") == "http://localhost:8765+shield"
    assert check_planner_spec("https://localhost:8765") == "https://localhost:8765"
    for bad, word in (("http://127.0.0.1", "port"), ("ftp://127.0.0.1:1", "http://"),
                      ("http://127.0.0.1:1/plan", "path"), ("http://127.0.0.1:99999", "port")):  # fmt: skip
        with pytest.raises(ValueError, match=word):
            check_planner_spec(bad)


def test_remote_planner_without_a_server_is_a_clear_error(tmp_path, capsys):
    import socket

    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with pytest.raises(ValueError, match="no answer"):
        planner_name(f"http://127.0.0.1:{port}")
    args = ["evaluate", "--planner", f"http://127.0.0.1:{port}", "--out", str(tmp_path / "r"), "--no-progress"]
    assert main(args) == 2
    assert "--planner" in capsys.readouterr().err and not (tmp_path / "r").exists()


@pytest.mark.parametrize("flag, value", [("--max-restarts", "-1"), ("--restart-window", "0"), ("--workers", "-2"),
                                         ("--time-limit", "0"), ("--http", "h2")])  # fmt: skip
def test_bad_server_limits_are_one_line_naming_the_flag(flag, value, capsys):
    assert main(["serve", "--planner", "fullthrottle", "--port", "0", flag, value]) == 2
    err = capsys.readouterr().err
    assert flag in err and "Traceback" not in err


# ---------------------------------------------------------------------- a real server process
def start_server(planner: str, *extra: str, env: dict | None = None, wait: float = 300.0):
    """Start ``sb3-graph serve --port 0`` and return ``(process, url)`` once it listens.

    ``--time-limit 60`` unless ``extra`` says otherwise: a step over it kills its worker and loses its stream,
    and these tests compare whole runs with in-process planning, so a stall of the shared machine must not
    count as an overrun (the time limit has its own tests in test_serve_workers.py).
    """
    return serve_process("--planner", planner, "--port", "0", "--time-limit", "60", *extra, env=env, wait=wait)


def stop_server(process) -> None:
    process.terminate()
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not SERVE_EXTRA:
        pytest.skip("the 'serve' extra (fastapi, uvicorn) is not installed")
    token_file = tmp_path_factory.mktemp("serve") / "token"
    token_file.write_text(TOKEN + "\n")
    process, url = start_server("aim", "--token-file", str(token_file), "--max-body", str(MAX_BODY),
                                "--max-streams", "8")  # fmt: skip
    try:
        yield SimpleNamespace(url=url, token_file=token_file)
    finally:
        stop_server(process)


@pytest.fixture
def client(server):
    client = PlannerClient(server.url, token=TOKEN)
    yield client
    client.disconnect()


@needs_server
def test_remote_aim_answers_recorded_scenes_as_in_process(server, client, recorded):
    local = AIMPlanner()
    local.reset(0)
    stream = client.open("4way", dt=0.2, seed=0)
    for scene in _scenes(recorded, "aim"):
        answer = client.step(stream, scene_to_wire(scene))
        np.testing.assert_array_equal(answer, local.act(scene), err_msg=str(scene.time))
    client.close(stream)


@needs_server
def test_streams_are_isolated(client, recorded):
    """Two interleaved streams each answer as a planner that saw only its own scenes."""
    scenes = _scenes(recorded, "aim")
    other = _scenes(recorded, "signal")  # another episode's traffic on the same intersection
    solo_a, solo_b = AIMPlanner(), AIMPlanner()
    solo_a.reset(0)
    solo_b.reset(0)
    a, b = client.open("4way", seed=0), client.open("4way", seed=0)
    try:
        for scene_a, scene_b in zip(scenes, other):
            np.testing.assert_array_equal(client.step(a, scene_to_wire(scene_a)), solo_a.act(scene_a))
            np.testing.assert_array_equal(client.step(b, scene_to_wire(scene_b)), solo_b.act(scene_b))
        # A reset stream forgets its reservations: it answers as a fresh planner, time starting over.
        client.reset(a, seed=0)
        fresh = AIMPlanner()
        fresh.reset(0)
        for scene in other[:20]:
            np.testing.assert_array_equal(client.step(a, scene_to_wire(scene)), fresh.act(scene))
    finally:
        client.close(a)
        client.close(b)
    with pytest.raises(RemotePlannerError) as caught:
        client.step(a, scene_to_wire(scenes[0]))
    assert caught.value.status == 404 and caught.value.field == "stream"


@needs_server
def test_bad_input_is_refused_naming_the_field_and_the_stream_goes_on(server, client, recorded):
    bench = _bench()
    scene = next(s for s in _scenes(recorded, "aim") if s.num_vehicles >= 3)
    good = scene_to_wire(scene)
    good["time"] = 100.0
    stream = client.open("4way", seed=0)
    try:
        client.step(stream, good)
        steps = 0
        for case in bench.bad_input_cases(good, MAX_BODY):
            status, reply = bench.send(server.url, case, stream, TOKEN, seq=client.seq[stream] + 1)
            assert (status, reply.get("field")) == (case.status, case.field), (case.name, status, reply)
            assert case.field in reply["error"], case.name
            good = {**good, "time": good["time"] + 0.2}
            assert client.step(stream, good).shape == (scene.num_vehicles,), case.name  # the next valid request
            steps += 1
        assert client.health()["status"] == "ok"
        assert client.request("POST", f"/streams/{stream}/reset", {"seed": 0})["steps"] == 0
    finally:
        client.close(stream)
    assert steps >= 25


@needs_server
def test_stream_limit_and_open_refusals(client):
    with pytest.raises(RemotePlannerError) as caught:
        client.open("3way")
    assert (caught.value.status, caught.value.field) == (422, "layout")
    with pytest.raises(RemotePlannerError) as caught:
        client.open("4way", dt=0.1)
    assert (caught.value.status, caught.value.field) == (422, "dt")
    before = client.health()["streams"]  # streams of other tests' planners still alive
    opened = []
    try:
        with pytest.raises(RemotePlannerError) as caught:
            for _ in range(9):  # the server takes 8
                opened.append(client.open("4way"))
        assert (caught.value.status, caught.value.field) == (429, "streams")
        assert len(opened) == 8 - before
    finally:
        for stream in opened:
            client.close(stream)
    assert client.health()["streams"] == before
    client.close(client.open("4way"))  # room again


@needs_server
def test_wrong_token_is_refused(server):
    for token in ("wrong", ""):
        with pytest.raises(RemotePlannerError) as caught:
            PlannerClient(server.url, token=token).version()
        assert (caught.value.status, caught.value.field) == (401, "authorization")
    assert PlannerClient(server.url, token="").health()["status"] == "ok"  # liveness needs no token


@needs_server
def test_evaluate_remote_gives_identical_metrics(server, tmp_path, monkeypatch):
    """``evaluate --planner http://...`` (and ``+shield``, shielded in the client) gives the in-process metrics."""
    monkeypatch.setenv(TOKEN_FILE_VARIABLE, str(server.token_file))
    monkeypatch.setenv(DEADLINE_VARIABLE, "60")  # no fallback on this shared machine: the identity is the point
    out = tmp_path / "report"
    words = ["aim", server.url, "aim+shield", server.url + "+shield"]
    args = ["evaluate", "--out", str(out), "--scenarios", "2", "--duration", "30", "--seed", "5", "--jobs", "1",
            "--no-progress"] + [a for w in words for a in ("--planner", w)]  # fmt: skip
    assert main(args) == 0
    metrics = pd.read_csv(out / "metrics.csv")
    vehicles = pd.read_csv(out / "vehicles.csv")
    remote = f"AIM@{server.url.removeprefix('http://')}"
    assert list(dict.fromkeys(metrics["planner"])) == ["AIM", remote, "AIM+shield", remote + "+shield"]
    drop = ["planner", "wall_s", "baseline", "remote_deadline_misses", "remote_retries", "remote_reopened"]
    assert (metrics.loc[metrics.planner.str.contains("@"), "remote_deadline_misses"] == 0).all()
    for local, far in (("AIM", remote), ("AIM+shield", remote + "+shield")):
        a = metrics[metrics.planner == local].drop(columns=drop, errors="ignore").reset_index(drop=True)
        b = metrics[metrics.planner == far].drop(columns=drop, errors="ignore").reset_index(drop=True)
        assert a["vehicles"].sum() > 10
        pd.testing.assert_frame_equal(a, b, check_exact=True)
        va = vehicles[vehicles.planner == local].drop(columns="planner").reset_index(drop=True)
        vb = vehicles[vehicles.planner == far].drop(columns="planner").reset_index(drop=True)
        pd.testing.assert_frame_equal(va, vb, check_exact=True)


@needs_server
def test_server_side_shield_and_gnn_answer_as_in_process(recorded):
    """The service (without HTTP) with ``--shield`` around the shipped GNN: per-stream shields, shared model; steps
    alternately as JSON and as fast-path frames, each answered as in process."""
    from envs.serve import frames
    from envs.serve.app import PlannerService
    from envs.serve.schema import OpenRequest

    model = str(ROOT / "envs" / "pretrained" / "coop_4way_fair" / "best_model.safetensors")
    service = PlannerService(model, ENV, shield=True)
    local = make_planner(model + "+shield")
    assert isinstance(local, Shield)
    local.reset(0)
    first = service.open(OpenRequest(layout="4way", seed=0))
    second = service.open(OpenRequest(layout="4way", seed=0))
    assert first.planner is not second.planner and first.planner.planner is second.planner.planner
    for seq, scene in enumerate(_scenes(recorded, "aim")[:60], start=1):
        if seq % 2:
            status, body = service.handle("step", first.id, json.dumps({**_through_json(scene), "seq": seq}).encode())
            reply = json.loads(body)
        else:
            frame = frames.encode_step(seq, scene.layout.name, scene.time, scene.route_names, scene.vehicle_id,
                                       scene.route, scene.arc, scene.speed, scene.length, scene.width)  # fmt: skip
            status, body = service.handle("frame", first.id, frame)
            reply = frames.decode_reply(body)
            reply["shield"]["overridden"] = reply["shield"]["overridden"].tolist()
        assert status == 200
        np.testing.assert_array_equal(reply["accelerations"], local.act(scene))
        assert reply["shield"]["overridden"] == local.last_overridden.tolist()
    assert first.planner.interventions == local.interventions and second.planner.interventions == 0


@needs_server
def test_openapi_schema_documents_the_scene_in_physical_units(client):
    schema = client.request("GET", "/openapi.json")
    vehicle = schema["components"]["schemas"]["Vehicle"]["properties"]
    assert set(vehicle) == {"id", "route", "arc", "speed", "length", "width"}
    assert "[m]" in vehicle["arc"]["description"] and "[m/s]" in vehicle["speed"]["description"]
    step = schema["paths"]["/streams/{stream}/step"]["post"]
    assert step["requestBody"]["content"]["application/json"]["schema"]["$ref"].endswith("/SceneIn")
    assert {"400", "401", "404", "409", "413", "415", "422", "429", "503"} <= set(step["responses"])


@needs_server
def test_version_names_the_routes_a_scene_may_use(client):
    # A client sends each vehicle's route and its arc along it: /version gives the names and lengths.
    from envs.simulation.layouts import build_layout

    layout = build_layout("4way")
    routes = client.version()["routes"]
    assert list(routes) == list(layout.route_names) and "south->north" in routes
    np.testing.assert_allclose(list(routes.values()), layout.length, atol=0.005)


@needs_server
def test_evaluate_behind_a_shielding_server_reports_its_counters(tmp_path, monkeypatch):
    """A server started with ``--shield``: the client reports the server's shield counters
    (:meth:`~envs.serve.client.RemotePlanner.stats`) in the metrics, as an in-process shield does."""
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    monkeypatch.setenv(TOKEN_FILE_VARIABLE, str(token_file))
    monkeypatch.setenv(DEADLINE_VARIABLE, "60")
    process, url = start_server("aim", "--shield", "--token-file", str(token_file))
    try:
        out = tmp_path / "report"
        args = ["evaluate", "--out", str(out), "--scenarios", "1", "--duration", "20", "--seed", "5", "--jobs", "1",
                "--no-progress", "--planner", "aim+shield", "--planner", url]  # fmt: skip
        assert main(args) == 0
    finally:
        stop_server(process)
    metrics = pd.read_csv(out / "metrics.csv").set_index("planner")
    local, far = metrics.loc["AIM+shield"], metrics.drop(index="AIM+shield").iloc[0]
    columns = ["shield_interventions", "shield_vehicle_steps", "shield_unresolved", "planner_errors", "crossed"]
    assert far[columns].tolist() == local[columns].tolist() and local["shield_vehicle_steps"] > 0


def test_the_service_compiles_the_fast_paths_kernels_before_its_first_stream():
    """A fresh server's first fast-path frame must not compile kernels: with cold caches that took over the
    default ``--time-limit`` of 1 s and the frame got 503. The service's warm-up decodes a frame and rebuilds its
    scene (checked in a fresh process, where nothing else has called the kernels)."""
    import subprocess
    import sys

    code = (
        "from envs.serve import frames, wire\n"
        "from envs.serve.app import PlannerService\n"
        "kernels = [frames._first_bad, wire._first_bad_row, wire._first_overlap]\n"
        "assert kernels and not any(k.signatures for k in kernels)\n"
        "PlannerService('pr', 'CoopIntersection4Way-v0')\n"
        "print(all(k.signatures for k in kernels))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "True"


@pytest.mark.skipif(not SERVE_EXTRA, reason="the 'serve' extra (fastapi, uvicorn) is not installed")
def test_a_scene_carries_its_capture_time_and_a_stale_one_is_refused(recorded, monkeypatch):
    """No ``captured`` or one from the future: 422 naming it; older than the shield's declared latency: refused with
    its age, and the same ``seq`` with a fresh scene is planned; without declared latency the age is not limited."""
    import msgspec

    from envs.planners.shield_bounds import ShieldBounds
    from envs.serve import app, frames
    from envs.serve.app import PlannerService
    from envs.serve.schema import OpenRequest

    monkeypatch.setattr(app, "_wall_clock", lambda: 5000.0)
    service = PlannerService("fifo", ENV, shield=True, shield_bounds=ShieldBounds(latency=0.1))
    assert service.info()["max_scene_age"] == 0.1 and service.prototype.bounds.latency == 0.1
    stream = service.open(OpenRequest(layout="4way", seed=0)).id
    scene = _scenes(recorded, "aim")[5]

    def send(captured, seq=1):
        wire = {**_through_json(scene), "seq": seq, "captured": captured}
        if captured is None:
            del wire["captured"]
        status, body = service.handle("step", stream, json.dumps(wire).encode())
        return status, json.loads(body)

    for captured, words in [(None, ["required"]), (5001.0, ["ahead", "future"]), (4999.8, ["0.200 s old", "0.1 s"])]:
        status, reply = send(captured)
        assert (status, reply["field"]) == (422, "captured"), reply
        assert all(word in reply["error"] for word in words), reply["error"]
    assert send(4999.95)[0] == 200  # the same seq, fresh (and a clock 0.03 s ahead is no future)
    assert send(5000.03, seq=2)[0] == 200
    # The fast path: the same checks, the same field.
    columns = (scene.layout.name, scene.time + 1, scene.route_names, scene.vehicle_id, scene.route, scene.arc,
               scene.speed, scene.length, scene.width)  # fmt: skip
    stale = frames.decode_reply(service.handle("frame", stream, frames.encode_step(3, *columns, 4999.0))[1])
    assert (stale["status"], stale["field"]) == (422, "captured") and "1.000 s old" in stale["error"]
    missing = msgspec.msgpack.decode(frames.encode_step(3, *columns, 5000.0))[:-1]  # an old client's frame
    refused = frames.decode_reply(service.handle("frame", stream, msgspec.msgpack.encode(missing))[1])
    assert (refused["status"], refused["field"]) == (422, "captured")
    assert service.handle("frame", stream, frames.encode_step(3, *columns, 5000.0))[0] == 200
    # No declared latency: any age is planned.
    plain = PlannerService("fifo", ENV, shield=True)
    assert plain.info()["max_scene_age"] is None
    other = plain.open(OpenRequest(layout="4way", seed=0)).id
    wire = {**_through_json(scene), "seq": 1, "captured": 10.0}
    assert plain.handle("step", other, json.dumps(wire).encode())[0] == 200
