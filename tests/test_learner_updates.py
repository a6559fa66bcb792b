"""Every graph learner makes the same updates as the recorded reference (issue #27).

``tests/data/learner_updates.safetensors`` was recorded by ``scripts/record_learner_updates.py``
with the learner before the speed work of issue #27 (commit 849ee98). Each algorithm's recorded
initial parameters are loaded into a fresh learner (the recorded state_dict keys must load), which
then trains on the same transitions with the code under test, once with the compiled kernels of
the relational layers and once with their PyTorch formulation: the trained parameters must agree
with the recording to float tolerance.
"""

import importlib.util
import warnings
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from sb3_graph.common.layers import use_compiled_kernels

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "learner_updates.safetensors"
_spec = importlib.util.spec_from_file_location("record_learner_updates", ROOT / "scripts" / "record_learner_updates.py")
record_learner_updates = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record_learner_updates)


@pytest.fixture(scope="module")
def reference():
    return load_file(str(FIXTURE))


@pytest.fixture(scope="module")
def data():
    return record_learner_updates.transitions()


def recorded(reference: dict, name: str, stage: str) -> dict:
    prefix = f"{name}/{stage}/"
    return {key[len(prefix) :]: value for key, value in reference.items() if key.startswith(prefix)}


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "pytorch"])
@pytest.mark.parametrize("name", record_learner_updates.ALGORITHMS)
def test_updates_match_recording(name, compiled, reference, data):
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = record_learner_updates.make_learner(name)
    model.policy.load_state_dict(recorded(reference, name, "initial"))
    previous = use_compiled_kernels(compiled)
    try:
        record_learner_updates.train(model, data)
    finally:
        use_compiled_kernels(previous)
    trained = recorded(reference, name, "trained")
    state = model.policy.state_dict()
    assert set(state) == set(trained)
    changed = 0
    for key, expected in trained.items():
        torch.testing.assert_close(state[key], expected, msg=f"{name} {key}")
        changed += int(not torch.equal(expected, recorded(reference, name, "initial")[key]))
    assert changed > 0  # the recording did train
