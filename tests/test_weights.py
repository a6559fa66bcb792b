"""The weights-only policy format and the safe reader of SB3 zips give the policy that was saved."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
import torch.nn as nn

from sb3_graph import TD3, GraphPolicy
from sb3_graph.files.policy_files import (
    POLICY_REGISTRY,
    PolicyFileError,
    kwargs_from_json,
    kwargs_to_json,
    load_policy,
    pickled_class_reference,
    read_sb3_zip,
    register_policy,
    resize_graph_policy,
    save_policy,
    space_from_json,
    space_to_json,
)
from sb3_graph.toy_envs import MaxNeighbourEnv


@pytest.fixture(scope="module")
def model():
    th.set_num_threads(1)
    kwargs = {"encoder_dim": 8, "conv_dims": (8, 4), "activation_fn": nn.Tanh, "pooling": "mean"}
    return TD3(GraphPolicy, MaxNeighbourEnv(), buffer_size=10, seed=0, policy_kwargs=kwargs)


def _same_actions(a, b, space):
    for seed in range(3):
        space.seed(seed)
        obs = space.sample()
        np.testing.assert_array_equal(a.predict(obs, deterministic=True)[0], b.predict(obs, deterministic=True)[0])


def test_weights_file_round_trip(model, tmp_path):
    path = save_policy(model.policy, tmp_path / "p.safetensors", "TD3", {"note": "test"})
    loaded = load_policy(path)
    assert loaded.description.policy_kwargs["activation_fn"] == {"class": "torch.nn.modules.activation.Tanh"}
    assert loaded.description.source == {"note": "test"}
    assert type(loaded.policy.actor.trunk.activation) is nn.Tanh
    _same_actions(model.policy, loaded.policy, model.observation_space)


def test_sb3_zip_read_without_unpickling_gives_the_same_policy(model, tmp_path):
    model.save(tmp_path / "m.zip")  # policy_kwargs holds a class: SB3 pickles the whole dict
    description, state = read_sb3_zip(tmp_path / "m.zip")
    assert description.policy_kwargs["activation_fn"] == {"class": "torch.nn.modules.activation.Tanh"}
    assert description.source["file"] == "m.zip"
    _same_actions(model.policy, load_policy(tmp_path / "m.zip").policy, model.observation_space)


def test_spaces_and_kwargs_as_json(model):
    for space in (model.observation_space, model.action_space):
        assert space_from_json(space_to_json(space)) == space
    kwargs = {"a": [1, (2, 3)], "act": nn.ReLU, "opt": th.optim.Adam, "n": None}
    assert kwargs_from_json(kwargs_to_json(kwargs)) == {"a": [1, [2, 3]], "act": nn.ReLU, "opt": th.optim.Adam,
                                                        "n": None}  # fmt: skip
    with pytest.raises(PolicyFileError, match="outside"):
        kwargs_to_json({"bad": __import__("collections").OrderedDict})
    with pytest.raises(ValueError, match="outside"):
        kwargs_from_json({"bad": {"class": "os.system"}})


def test_class_references_are_read_from_opcodes_only():
    import base64
    import pickle

    assert pickled_class_reference(base64.b64encode(pickle.dumps(GraphPolicy)).decode()) == (
        GraphPolicy.__module__,
        "GraphPolicy",
    )
    assert pickled_class_reference(base64.b64encode(pickle.dumps(GraphPolicy, protocol=2)).decode()) == (
        GraphPolicy.__module__,
        "GraphPolicy",
    )
    for other in (pickle.dumps({"a": GraphPolicy}), pickle.dumps(print), b"not a pickle"):
        reference = pickled_class_reference(base64.b64encode(other).decode())
        assert reference is None or reference == ("builtins", "print")


def test_registry_is_per_algorithm(tmp_path, model):
    from sb3_graph.registry import ALGORITHMS

    assert POLICY_REGISTRY["TD3"] == {"GraphPolicy": "sb3_graph.policies:GraphPolicy"}
    assert list(POLICY_REGISTRY) == [entry.name for entry in ALGORITHMS.values()]  # every algorithm exports
    register_policy("MyAlgo", "GraphPolicy", "sb3_graph.policies:GraphPolicy")
    try:
        assert "MyAlgo" in POLICY_REGISTRY
    finally:
        POLICY_REGISTRY.pop("MyAlgo")
    path = save_policy(model.policy, tmp_path / "p.safetensors", "TD3")
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), "pt") as handle:
        metadata, tensors = handle.metadata(), {k: handle.get_tensor(k) for k in handle.keys()}
    save_file(tensors, str(tmp_path / "q.safetensors"), {"sb3_graph": metadata["sb3_graph"].replace("TD3", "PPO")})
    with pytest.raises(PolicyFileError, match="PPO/GraphPolicy is not an allowed planner policy"):
        load_policy(tmp_path / "q.safetensors")


def test_a_policy_registered_under_the_old_module_path_is_allowed_in_files():
    """Plugins register their policy classes with ``sb3_graph.weights.register_policy``: the old path
    still registers into the one allow-list that the policy-file readers consult."""
    import sb3_graph.weights
    from sb3_graph.files.policy_files import registered_policy
    from sb3_graph.td3.policies import GraphPolicy

    with pytest.raises(PolicyFileError, match="MyAlgo/MyPolicy"):
        registered_policy("MyAlgo", "MyPolicy")
    sb3_graph.weights.register_policy("MyAlgo", "MyPolicy", "sb3_graph.policies:GraphPolicy")
    try:
        assert registered_policy("MyAlgo", "MyPolicy") is GraphPolicy
    finally:
        POLICY_REGISTRY.pop("MyAlgo")


def test_a_graph_policy_resized_to_larger_graphs_acts_the_same_on_the_same_graph(model, tmp_path):
    small = load_policy(save_policy(model.policy, tmp_path / "p.safetensors", "TD3"))
    large = resize_graph_policy(small, 20, 60, "p.safetensors")
    assert (large.policy.observation_space.max_nodes, large.policy.observation_space.max_edges) == (20, 60)
    assert large.policy.action_space.shape == (20,)
    assert large.description.source["resized_from"] == {"max_nodes": 8, "max_edges": 25}
    space = model.observation_space
    for seed in range(3):
        space.seed(seed)
        obs = space.sample()
        n = int(obs["node_mask"].sum())
        wide = large.policy.observation_space.encode(*space.decode(obs))
        act_small = small.policy.predict(obs, deterministic=True)[0][:n]
        np.testing.assert_allclose(large.policy.predict(wide, deterministic=True)[0][:n], act_small, atol=1e-6)


def test_export_resizes_on_request_and_names_a_bad_size(model, tmp_path, capsys):
    from sb3_graph.cli import main

    model.save(tmp_path / "m.zip")
    out = tmp_path / "wide.safetensors"
    assert main(["export", str(tmp_path / "m.zip"), str(out), "--max-nodes", "20", "--max-edges", "60"]) == 0
    assert load_policy(out).policy.observation_space.max_nodes == 20
    assert main(["export", str(tmp_path / "m.zip"), str(tmp_path / "bad.safetensors"), "--max-nodes", "0"]) == 2
    assert "--max-nodes" in capsys.readouterr().err and not (tmp_path / "bad.safetensors").exists()
