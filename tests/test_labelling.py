"""Expert labels on an executor, resumable (sb3_graph.common.labelling), on the toy task."""

import json
import warnings

import numpy as np
import pytest
import yaml
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

import sb3_graph
from sb3_graph.cli import main
from sb3_graph.common.cloning import Demonstrations
from sb3_graph.common.executors import LocalExecutor
from sb3_graph.common.labelling import LabellingJob, ShardedCollector
from sb3_graph.toy_envs import MAX_NEIGHBOUR_ID, make_expert

JOB = LabellingJob(MAX_NEIGHBOUR_ID, {"min_nodes": 0}, "exact", "sb3_graph.toy_envs:make_expert", ("sb3_graph",))


def td3(n_envs=3, seed=0):
    """A TD3 learner whose VecEnv is seeded ``seed`` (the model reseeds it with its own, as ``sb3-graph train``'s)."""
    env = make_vec_env(MAX_NEIGHBOUR_ID, n_envs=n_envs, seed=seed, env_kwargs={"min_nodes": 0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = sb3_graph.TD3("GraphPolicy", env, seed=seed, learning_starts=0, batch_size=16, buffer_size=400,
                              policy_kwargs=dict(encoder_dim=16, conv_dims=[16, 16]))  # fmt: skip
    model.set_logger(configure(None, []))
    return model


def test_round_zero_is_the_lockstep_collection_bit_for_bit():
    """Shards of one environment each, stacked, hold what one VecEnv of all of them records in lockstep
    (episodes of 8 steps end inside the 20: the terminal observations are merged in step order)."""
    lockstep = td3(seed=5)
    expert = make_expert("exact", lockstep.get_env())
    recorded = sb3_graph.behaviour_clone(lockstep, expert, transitions=60, gradient_steps=0, critic_steps=0,
                                         record=True)["demonstrations"].arrays()  # fmt: skip
    sharded = ShardedCollector(td3(seed=5), JOB, seed=5)(0, 1.0, 20).arrays()
    assert recorded.keys() == sharded.keys()
    assert recorded["terminal_index"].shape[0] == 6  # each of 3 environments ended 2 episodes
    for name in recorded:
        np.testing.assert_array_equal(recorded[name], sharded[name], err_msg=name)


def test_processes_label_what_this_process_labels():
    model = td3(n_envs=2)
    here = ShardedCollector(model, JOB, seed=1)(1, 1.0, 6).arrays()
    with LocalExecutor(workers=2) as pool:
        there = ShardedCollector(model, JOB, seed=1, executor=pool)(1, 1.0, 6).arrays()
    for name in here:
        np.testing.assert_array_equal(here[name], there[name], err_msg=name)


def test_a_dask_cluster_labels_what_this_process_labels():
    distributed = pytest.importorskip("distributed")  # in the test extra: runs in CI
    model = td3(n_envs=2)
    here = ShardedCollector(model, JOB, seed=1)(0, 1.0, 5).arrays()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        there = ShardedCollector(model, JOB, seed=1, executor="dask", address=cluster.scheduler_address)(0, 1.0, 5)
    for name in here:
        np.testing.assert_array_equal(here[name], there.arrays()[name], err_msg=name)


def test_each_round_starts_new_episodes_from_its_own_seeds():
    collector = ShardedCollector(td3(n_envs=2), JOB, seed=0)
    first, second = collector(0, 1.0, 3).arrays(), collector(1, 1.0, 3).arrays()
    assert not np.array_equal(first["obs/x"], second["obs/x"])
    again = ShardedCollector(td3(n_envs=2), JOB, seed=2)(0, 1.0, 3).arrays()  # round 1 of seed 0 = round 0 of seed 2
    np.testing.assert_array_equal(second["obs/x"], again["obs/x"])


def test_a_learner_round_mixes_the_policy_and_labels_every_state():
    np.random.seed(0)  # noqa: NPY002 (the model's stream, as SB3 seeds it)
    model = td3(n_envs=2)
    result = sb3_graph.behaviour_clone(model, lambda obs: None, transitions=80, gradient_steps=4, batch_size=8,
                                       rounds=2, beta=lambda k: 0.5**k,
                                       collector=ShardedCollector(model, JOB, seed=0))  # fmt: skip
    assert result["transitions"] == 80
    assert 0.5 < result["expert_share"] < 1.0  # round 0 all expert, round 1 about half


def test_kept_shards_are_read_back_and_only_missing_ones_labelled(tmp_path):
    model = td3(n_envs=3)
    first = ShardedCollector(model, JOB, seed=0, folder=tmp_path)
    made = first(0, 1.0, 4).arrays()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"round-0-env-{i}.npz" for i in range(3)]
    (tmp_path / "round-0-env-1.npz").unlink()
    (tmp_path / "round-0-env-2.npz").write_bytes(b"cut short")
    again = ShardedCollector(model, JOB, seed=0, folder=tmp_path)
    read = again(0, 1.0, 4).arrays()
    assert again.labelled == [0]
    for name in made:
        np.testing.assert_array_equal(made[name], read[name], err_msg=name)
    assert (tmp_path / "round-0-env-2.npz").read_bytes() == b"cut short"  # never overwritten
    assert (tmp_path / "round-0-env-1.npz").is_file()
    third = ShardedCollector(model, JOB, seed=0, folder=tmp_path)
    (tmp_path / "round-0-env-2.npz").unlink()
    third(0, 1.0, 4)
    fourth = ShardedCollector(model, JOB, seed=0, folder=tmp_path)
    fourth(0, 1.0, 4)
    assert fourth.labelled == []  # all read


def test_stack_refuses_parts_of_other_lengths():
    collector = ShardedCollector(td3(n_envs=1), JOB, seed=0)
    with pytest.raises(ValueError, match="differ in steps"):
        Demonstrations.stack([collector(0, 1.0, 3), collector(0, 1.0, 4)])


def test_bad_settings_name_the_setting():
    with pytest.raises(ValueError, match="labelling executor must be one of local, dask, ray, got 'mpi'"):
        ShardedCollector(td3(n_envs=1), JOB, seed=0, executor="mpi")
    with pytest.raises(ValueError, match="labelling workers must be an integer >= 1, got 0"):
        ShardedCollector(td3(n_envs=1), JOB, seed=0, workers=0)
    with pytest.raises(ValueError, match="a collector keeps its own rounds"):
        sb3_graph.behaviour_clone(td3(n_envs=1), lambda obs: None, transitions=4, gradient_steps=0, record=True,
                                  collector=ShardedCollector(td3(n_envs=1), JOB, seed=0))  # fmt: skip


def test_train_labels_on_workers_and_a_second_run_labels_nothing(tmp_path, capsys):
    """``sb3-graph train --label-jobs 2 --pretrain-cache``: the shards land in the cache; a second seed-equal run
    reuses the clone; a run that lost one shard labels that shard alone."""
    config = tmp_path / "toy.yml"
    entry = {"n_timesteps": 40, "policy": "GraphPolicy", "learning_starts": 20, "batch_size": 16, "buffer_size": 500,
             "n_envs": 2, "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])", "pretrain_from": "exact",
             "pretrain_transitions": 24, "pretrain_rounds": 2, "pretrain_beta": 0.5, "pretrain_steps": 4,
             "env_kwargs": {"min_nodes": 0}}  # fmt: skip
    config.write_text(yaml.safe_dump({MAX_NEIGHBOUR_ID: entry}))
    cache = tmp_path / "labels"

    def train(out):
        argv = ["train", "--config", str(config), "--env", MAX_NEIGHBOUR_ID, "--out", str(tmp_path / out), "--seed",
                "3", "--eval-freq", "40", "--eval-episodes", "1", "--no-progress", "--pretrain-cache", str(cache),
                "--label-jobs", "2"]  # fmt: skip
        assert main(argv) == 0
        return json.loads((tmp_path / out / "run.json").read_text())["pretrain"]

    first = train("a")
    assert first["cache"] == "none" and first["rounds_labelled"] == [0, 1] and first["transitions"] == 24
    shards = sorted(p.name for p in (cache / first["demonstrations_folder"]).iterdir())
    assert shards == ["round-0-env-0.npz", "round-0-env-1.npz", "round-1-env-0.npz", "round-1-env-1.npz"]
    assert train("b")["cache"] == "clone"
    (cache / first["demonstrations_folder"] / "round-1-env-0.npz").unlink()
    third = train("c")
    assert third["cache"] == "none" and third["rounds_labelled"] == [1]
    assert "labelled on local, 2 workers" in capsys.readouterr().out
