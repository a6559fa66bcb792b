"""The simulation drives the same trajectories as the recorded reference (issue #16).

``tests/data/simulation_regression.npz`` was recorded by ``scripts/record_regression.py`` with
the code before the simulation was vectorized further. Each case is replayed with the code under
test: positions, speeds, observations and reward terms agree to floating-point tolerance; vehicle
ids, edges, collisions and every metric event agree exactly.
"""

import importlib.util
import warnings
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "simulation_regression.npz"
_spec = importlib.util.spec_from_file_location("record_regression", ROOT / "scripts" / "record_regression.py")
record_regression = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record_regression)

# Fields compared exactly (ids, rows, events) and to tolerance (continuous values).
EXACT = ("vehicle_id", "edge_index", "edge_type", "collisions", "waiting", *record_regression.EVENTS)
CLOSE = {"position": 1e-7, "speed": 1e-7, "reward": 1e-7, "x": 1e-5}


@pytest.fixture(scope="module")
def reference():
    with np.load(FIXTURE) as data:
        return {key: data[key] for key in data.files}


@pytest.mark.parametrize("case", list(record_regression.CASES))
def test_replay_matches_recording(case, reference):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = record_regression.run_case(case)
    for key in (*EXACT, *CLOSE):
        np.testing.assert_array_equal(got[f"{key}_count"], reference[f"{case}/{key}_count"], err_msg=f"{case} {key}")
    for key in EXACT:
        np.testing.assert_array_equal(got[key], reference[f"{case}/{key}"], err_msg=f"{case} {key}")
    for key, atol in CLOSE.items():
        np.testing.assert_allclose(got[key], reference[f"{case}/{key}"], rtol=1e-9, atol=atol, err_msg=f"{case} {key}")


def test_reference_has_collisions_and_governor():
    """The cases exercise what the faster code must keep: collisions, the governor, spawning."""
    with np.load(FIXTURE) as data:
        assert sum(int(data[f"{c}/collisions_count"].sum()) for c in record_regression.CASES) > 0
        assert sum(int(data[f"{c}/governed_count"].sum()) for c in record_regression.CASES) > 0
        assert sum(int(data[f"{c}/entered_count"].sum()) for c in record_regression.CASES) > 0
