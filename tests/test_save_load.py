"""Model, policy and replay buffer survive save/load."""

import base64
import json
import zipfile

import numpy as np
import stable_baselines3
import torch

from sb3_graph import TD3, GraphPolicy, GraphReplayBuffer
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)


def observations(env, count=5):
    env.reset(seed=3)
    return [env.step(env.action_space.sample())[0] for _ in range(count)]


def test_model_save_load_predict(tmp_path):
    env = MaxNeighbourEnv()
    model = TD3(
        "GraphPolicy",
        env,
        learning_starts=10,
        batch_size=8,
        seed=0,
        policy_kwargs=dict(encoder_dim=16, conv_dims=[16], pooling="mean"),
    )
    model.learn(30)
    obs = observations(env)
    before = [model.predict(o, deterministic=True)[0] for o in obs]
    model.save(tmp_path / "planner")
    loaded = TD3.load(tmp_path / "planner", env=env)
    assert loaded.policy.pooling == "mean" and loaded.policy.graph_kwargs["conv_dims"] == [16]
    for o, a in zip(obs, before):
        np.testing.assert_allclose(loaded.predict(o, deterministic=True)[0], a)
        n = int(o["node_mask"].sum())
        assert np.all(a[n:] == 0) and a.shape == env.action_space.shape
    batched = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
    np.testing.assert_allclose(
        loaded.predict(batched, deterministic=True)[0], np.stack(before), rtol=1e-5, atol=1e-6
    )
    loaded.learn(20)  # training continues
    # Saved with sb3_graph.TD3, loadable by plain SB3 too.
    stable_baselines3.TD3.load(tmp_path / "planner", env=env)


def test_policy_save_load(tmp_path):
    env = MaxNeighbourEnv()
    model = TD3("GraphPolicy", env, seed=0)
    model.policy.save(tmp_path / "policy.pt")
    policy = GraphPolicy.load(tmp_path / "policy.pt")
    o = observations(env, 1)[0]
    np.testing.assert_allclose(policy.predict(o)[0], model.predict(o, deterministic=True)[0])


def test_replay_buffer_save_load(tmp_path):
    env = MaxNeighbourEnv()
    model = TD3("GraphPolicy", env, learning_starts=10, batch_size=8, buffer_size=50, seed=0)
    model.learn(70)  # the ring wraps
    model.save_replay_buffer(tmp_path / "buffer")
    fresh = TD3("GraphPolicy", env, seed=1)
    fresh.load_replay_buffer(tmp_path / "buffer")
    assert isinstance(fresh.replay_buffer, GraphReplayBuffer)
    assert fresh.replay_buffer.full and fresh.replay_buffer.pos == model.replay_buffer.pos
    np.random.seed(0)  # noqa: NPY002 (SB3 samples with the global generator)
    a = model.replay_buffer.sample(16)
    np.random.seed(0)  # noqa: NPY002 (SB3 samples with the global generator)
    b = fresh.replay_buffer.sample(16)
    for t1, t2 in zip(a.observations[:5], b.observations[:5]):
        torch.testing.assert_close(t1, t2)
    torch.testing.assert_close(a.actions, b.actions)
    torch.testing.assert_close(a.rewards, b.rewards)
    fresh.learn(10, reset_num_timesteps=False)


def test_model_saved_under_the_old_module_paths_loads(tmp_path, monkeypatch):
    """Models saved before ``spaces`` and ``buffers`` moved into ``sb3_graph.common`` (the shipped
    planners among them) name ``sb3_graph.spaces.GraphSpace`` and ``sb3_graph.buffers.GraphReplayBuffer``
    in their pickles and their ``:type:`` strings: they still load, and still read without unpickling."""
    from sb3_graph.common.spaces import GraphSpace
    from sb3_graph.files.policy_files import read_sb3_zip

    env = MaxNeighbourEnv()
    model = TD3("GraphPolicy", env, seed=0, policy_kwargs=dict(encoder_dim=8, conv_dims=[8]))
    with monkeypatch.context() as patch:  # pickled as the old files were (needs the re-exports to exist)
        patch.setattr(GraphSpace, "__module__", "sb3_graph.spaces")
        patch.setattr(GraphReplayBuffer, "__module__", "sb3_graph.buffers")
        model.save(tmp_path / "old")
    with zipfile.ZipFile(tmp_path / "old.zip") as archive:
        data = json.loads(archive.read("data"))
    assert data["observation_space"][":type:"] == "<class 'sb3_graph.spaces.GraphSpace'>"
    assert b"sb3_graph.buffers" in base64.b64decode(data["replay_buffer_class"][":serialized:"])

    loaded = TD3.load(tmp_path / "old", env=env)
    assert type(loaded.observation_space) is GraphSpace and loaded.replay_buffer_class is GraphReplayBuffer
    o = observations(env, 1)[0]
    np.testing.assert_allclose(loaded.predict(o, deterministic=True)[0], model.predict(o, deterministic=True)[0])
    description, state = read_sb3_zip(tmp_path / "old.zip")
    assert description.observation_space["type"] == "GraphSpace"
    assert set(state) == set(model.policy.state_dict())
