"""Property tests of the parsers that read what users hand over: arbitrary input gives a result
or a clear error (a ``ValueError`` naming what is wrong), never another exception."""

from __future__ import annotations

import json
import math
import string

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from envs.ind.format import IndDataError, parse_recordings, recording_file
from envs.ind.loader import load_recording
from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording
from envs.simulation.config import RULES, validate_config
from envs.simulation.env import CoopIntersectionEnv
from envs.simulation.traffic import Scenario
from sb3_graph.files.experiment_files import ExperimentError, check_entry, resolve_object
from sb3_graph.files.policy_files import PolicyDescription, PolicyFileError, space_from_json
from sb3_graph.files.safe_values import UnsafeValueError, parse_value


def examples(count: int):
    """Hypothesis settings: ``count`` examples, no deadline, no example database (the tests leave
    no .hypothesis folder in the working tree)."""
    return settings(
        max_examples=count, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
    )


FAST = examples(60)

# JSON values of every kind, numbers at the edges included.
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([10**400, -(10**400), 2**63, -(2**63) - 1]),  # JSON integers have no size limit
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
json_values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
ROUTES = ["south->north", "west->east", "north->south", "east->west", "south->west", "nowhere"]


def _number_or_junk():
    return st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(min_value=-(2**70), max_value=2**70),
        scalars,
    )


vehicle = st.fixed_dictionaries(
    {"id": st.one_of(st.integers(min_value=-(2**70), max_value=2**70), scalars), "route": st.sampled_from(ROUTES)},
    optional={key: _number_or_junk() for key in ("time", "speed", "length", "width")} | {"extra": scalars},
)
scenario_dicts = st.fixed_dictionaries(
    {
        "layout": st.one_of(st.sampled_from(["4way", "3way", "inD", "roundabout"]), scalars),
        "duration": _number_or_junk(),
        "vehicles": st.one_of(st.lists(vehicle, max_size=4), json_values),
    },
    optional={"format": st.one_of(st.just("sb3-graph-scenario"), scalars), "seed": scalars, "meta": json_values},
)


# ---------------------------------------------------------------- scenario files
@FAST
@given(data=st.one_of(scenario_dicts, json_values))
def test_scenario_from_any_json_is_a_scenario_or_a_clear_error(data):
    try:
        scenario = Scenario.from_dict(data, source="s.json")
    except ValueError as error:
        assert str(error).startswith("s.json: ")
        return
    assert scenario.num_vehicles == len(data["vehicles"])
    assert np.isfinite(scenario.time).all() and (scenario.time >= 0).all()
    assert Scenario.from_dict(json.loads(json.dumps(scenario.to_dict())), "again").to_dict() == scenario.to_dict()


@FAST
@given(content=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)))
def test_scenario_file_of_any_bytes_is_a_clear_error(tmp_path, content):
    path = tmp_path / "scenario.json"
    path.write_bytes(content)
    try:
        Scenario.load(path)
    except ValueError as error:
        assert str(error).startswith(str(path))


def test_deeply_nested_scenario_file_is_a_clear_error(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match="deep.json"):
        Scenario.load(path)


# ---------------------------------------------------------------- environment configuration
config_values = st.one_of(
    json_values,
    st.integers(min_value=-5, max_value=2**40),
    st.floats(min_value=-2.0, max_value=200.0),
    st.sampled_from([np.int64(8), np.float32(0.5), np.int32(4), np.bool_(True)]),
    st.tuples(st.floats(-1, 2), st.floats(-1, 2)),
)


@examples(150)
@given(config=st.dictionaries(st.sampled_from(sorted(RULES) + ["unknown_key"]), config_values, max_size=4))
def test_env_config_is_valid_or_names_the_key(config):
    defaults = CoopIntersectionEnv.default_config()
    try:
        merged = validate_config(config, defaults)
    except ValueError as error:
        assert any(repr(key) in str(error) for key in [*config, "simulation_frequency"])
        return
    json.dumps({k: v for k, v in merged.items()})  # plain Python values, NumPy scalars converted
    assert 1 <= merged["max_vehicles"] <= 1024


@examples(25)
@given(config=st.dictionaries(st.sampled_from(["max_vehicles", "max_edges", "duration", "spawn_probability"]),
                              config_values, max_size=2))  # fmt: skip
def test_env_accepts_or_refuses_before_stepping(config):
    try:
        expected = validate_config(config, CoopIntersectionEnv.default_config())
    except ValueError:
        expected = None
    try:
        env = CoopIntersectionEnv(config=config)
    except ValueError as error:  # refused exactly when the config check refuses, naming a key
        assert expected is None, config
        assert any(repr(key) in str(error) for key in [*config, "simulation_frequency"]), str(error)
        return
    assert expected is not None, config
    assert {key: env.config[key] for key in config} == {key: expected[key] for key in config}
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    obs, reward, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
    assert env.observation_space.contains(obs) and np.isfinite(reward)
    assert obs["x"].shape[0] == env.config["max_vehicles"] and int(obs["node_mask"].sum()) <= env.config["max_vehicles"]


# ---------------------------------------------------------------- inD recordings
SITE = SyntheticSite(centre=(10.0, -20.0), rotation_deg=5.0, location_id=1)


@pytest.fixture(scope="module")
def recording_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ind_valid")
    write_recording(folder, make_recording(7, default_vehicles(seed=0, num=4), SITE))
    return {kind: recording_file(folder, 7, kind).read_text() for kind in ("tracks", "tracksMeta", "recordingMeta")}


cells = st.one_of(
    st.text(alphabet=string.ascii_letters + string.digits + ".-eE ,\"'", max_size=6),
    st.sampled_from(["", "nan", "inf", "1e999", "-0", "3.5", "NaN"]),
)


@examples(40)
@given(
    kind=st.sampled_from(["tracks", "tracksMeta", "recordingMeta"]),
    row=st.integers(min_value=0, max_value=30),
    column=st.integers(min_value=0, max_value=16),
    value=cells,
    cut=st.one_of(st.none(), st.integers(min_value=0, max_value=4000)),
)
def test_ind_recording_with_a_changed_cell_or_cut_loads_or_names_the_file(
    tmp_path_factory, recording_files, kind, row, column, value, cut
):
    folder = tmp_path_factory.mktemp("ind")
    for name, text in recording_files.items():
        lines = text.splitlines()
        if name == kind:
            k = 1 + row % max(len(lines) - 1, 1)
            fields = lines[k].split(",")
            fields[column % len(fields)] = value
            lines[k] = ",".join(fields)
            text = "\n".join(lines) + "\n"
            if cut is not None:
                text = text[: cut % (len(text) + 1)]
        recording_file(folder, 7, name).write_text(text)
    try:
        recording = load_recording(folder, 7)
    except IndDataError as error:
        assert "_" in str(error) and ".csv" in str(error)  # names the file
        return
    assert np.isfinite(recording.tracks[["xCenter", "yCenter", "speed"]].to_numpy()).all()
    assert recording.frame_rate > 0 and math.isfinite(recording.duration)


@examples(40)
@given(contents=st.tuples(st.binary(max_size=120), st.binary(max_size=120), st.binary(max_size=120)))
def test_ind_files_of_any_bytes_are_a_clear_error(tmp_path_factory, contents):
    folder = tmp_path_factory.mktemp("ind_bytes")
    for kind, content in zip(("tracks", "tracksMeta", "recordingMeta"), contents):
        recording_file(folder, 7, kind).write_bytes(content)
    with pytest.raises(IndDataError, match=r"\.csv"):
        load_recording(folder, 7)


def test_gzipped_and_truncated_ind_files_are_named(tmp_path, recording_files):
    import gzip

    for kind, text in recording_files.items():
        recording_file(tmp_path, 7, kind).write_text(text)
    tracks = recording_file(tmp_path, 7, "tracks")
    tracks.write_bytes(gzip.compress(recording_files["tracks"].encode()))
    with pytest.raises(IndDataError, match="07_tracks.csv: the file is gzip-compressed"):
        load_recording(tmp_path, 7)
    lines = recording_files["tracks"].splitlines()
    tracks.write_text("\n".join(lines[: len(lines) // 2]) + "\n")  # cut after a row, mid-track
    with pytest.raises(IndDataError, match="07_tracks.csv: track .* truncated"):
        load_recording(tmp_path, 7)
    tracks.write_text("\n".join(lines[: len(lines) // 2]) + "\n" + lines[len(lines) // 2][:9])  # cut mid-row
    with pytest.raises(IndDataError, match="07_tracks.csv: column .* line"):
        load_recording(tmp_path, 7)
    tracks.write_text(recording_files["tracks"])
    frame = pd.read_csv(recording_file(tmp_path, 7, "tracksMeta"), dtype=str)
    frame.loc[1, "initialFrame"] = "soon"
    frame.to_csv(recording_file(tmp_path, 7, "tracksMeta"), index=False)
    with pytest.raises(IndDataError, match="07_tracksMeta.csv: column 'initialFrame', line 3: 'soon'"):
        load_recording(tmp_path, 7)


@examples(200)
@given(text=st.text(alphabet="0123456789-, x", max_size=20) | st.sampled_from(["0-99999999999", "1-1000000"]))
def test_recording_lists_parse_or_name_the_option(text):
    try:
        ids = parse_recordings(text)
    except ValueError as error:
        assert str(error).startswith("recordings:")
        return
    assert ids == sorted(set(ids)) and min(ids) >= 0


# ---------------------------------------------------------------- experiment files and policy files
python_text = st.one_of(
    st.text(max_size=40),
    st.sampled_from(
        [
            "dict(a=1, b=(2, 3))",
            "nn.ReLU",
            "__import__('os').system('true')",
            "importlib.import_module('os').system",
            "dict(f=open('x'))",
            "[1, 2, {'a': -3.5}]",
            "sb3_graph.files.experiment_files.importlib",
            "th.nn.Tanh.__subclasses__",
            "(lambda: 1)()",
        ]
    ),
)


@examples(300)
@given(text=python_text)
def test_python_valued_strings_parse_or_are_refused(text):
    try:
        value = parse_value(text, "policy_kwargs")
    except UnsafeValueError as error:
        assert str(error).startswith("policy_kwargs: ")
        return
    assert value is None or isinstance(value, (int, float, str, tuple, list, dict, type))


@examples(200)
@given(entry=st.dictionaries(st.sampled_from(["n_timesteps", "gamma", "learning_rate", "train_freq", "n_envs",
                                              "batch_size", "policy_kwargs", "env_kwargs"]),  # fmt: skip
                             json_values, max_size=4))
def test_experiment_entries_are_checked_or_name_the_key(entry):
    try:
        checked = check_entry(entry)
        for key in ("policy_kwargs",):
            if key in checked:
                resolve_object(checked[key], key)
    except ExperimentError as error:
        assert any(key in str(error) for key in entry)


@FAST
@given(data=json_values)
def test_policy_file_metadata_is_read_or_refused(data):
    with pytest.raises(PolicyFileError):
        PolicyDescription.from_json(json.dumps(data), "p.safetensors")
    try:
        space_from_json(data)
    except ValueError:
        pass


@FAST
@given(shape=st.lists(st.integers(-2, 70), max_size=3), low=scalars, high=scalars, dtype=scalars)
def test_box_spaces_from_json_are_built_or_refused(shape, low, high, dtype):
    assume(not (isinstance(low, float) and math.isnan(low)))
    try:
        space = space_from_json({"type": "Box", "shape": shape, "low": low, "high": high, "dtype": dtype})
    except ValueError:
        return
    assert list(space.shape) == shape

