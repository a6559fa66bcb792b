"""Every algorithm alias (TD3, DDPG, SAC, TQC, CrossQ, PPO, A2C): construction, learning, save/load,
stock SB3 classes with the graph policies, and padded slots that never change a loss."""

import warnings

import numpy as np
import pytest
import sb3_contrib
import stable_baselines3
import torch
from stable_baselines3.common.buffers import DictReplayBuffer, DictRolloutBuffer
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import sb3_graph
from sb3_graph import (
    GraphActorCriticPolicy,
    GraphCrossQPolicy,
    GraphPolicy,
    GraphReplayBuffer,
    GraphRolloutBuffer,
    GraphSACPolicy,
    GraphTQCPolicy,
)
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)

SMALL = dict(encoder_dim=16, conv_dims=[16, 16])
OFF_POLICY = dict(learning_starts=10, batch_size=8, buffer_size=200)
# name: (alias, stock class, policy class, constructor arguments of a tiny run)
ALGOS = {
    "TD3": (sb3_graph.TD3, stable_baselines3.TD3, GraphPolicy, OFF_POLICY),
    "DDPG": (sb3_graph.DDPG, stable_baselines3.DDPG, GraphPolicy, OFF_POLICY),
    "SAC": (sb3_graph.SAC, stable_baselines3.SAC, GraphSACPolicy, OFF_POLICY),
    "TQC": (sb3_graph.TQC, sb3_contrib.TQC, GraphTQCPolicy, OFF_POLICY),
    "CrossQ": (sb3_graph.CrossQ, sb3_contrib.CrossQ, GraphCrossQPolicy, OFF_POLICY),
    "PPO": (sb3_graph.PPO, stable_baselines3.PPO, GraphActorCriticPolicy, dict(n_steps=16, batch_size=8, n_epochs=2)),
    "A2C": (sb3_graph.A2C, stable_baselines3.A2C, GraphActorCriticPolicy, dict(n_steps=8)),
}
ON_POLICY = ("PPO", "A2C")


def tiny(name: str, **extra):
    alias, _, _, kwargs = ALGOS[name]
    policy_kwargs = dict(SMALL, n_quantiles=5) if name == "TQC" else dict(SMALL)
    return alias(
        "GraphPolicy",
        extra.pop("env", None) or MaxNeighbourEnv(min_nodes=0),
        seed=0,
        policy_kwargs=policy_kwargs,
        **kwargs,
        **extra,
    )


@pytest.mark.parametrize("name", ALGOS)
def test_alias_builds_graph_policy_and_buffer_and_trains(name):
    # min_nodes=0: batches hold empty graphs, and the backward pass must take them.
    model = tiny(name)
    _, _, policy_class, _ = ALGOS[name]
    assert type(model.policy) is policy_class
    buffer = model.rollout_buffer if name in ON_POLICY else model.replay_buffer
    assert isinstance(buffer, GraphRolloutBuffer if name in ON_POLICY else GraphReplayBuffer)
    model.learn(40)
    losses = {k: v for k, v in model.logger.name_to_value.items() if "loss" in k}
    assert losses and all(np.isfinite(v) for v in losses.values()), losses
    assert model.policy.__class__.__name__ in {c.__name__ for c in sb3_graph.POLICY_CLASSES}


@pytest.mark.parametrize("name", ALGOS)
def test_stock_class_takes_the_graph_policy(name):
    _, stock, policy_class, kwargs = ALGOS[name]
    extra = {"replay_buffer_class": GraphReplayBuffer} if name == "CrossQ" else {}  # see crossq/policies.py
    policy_kwargs = dict(SMALL, n_quantiles=5) if name == "TQC" else dict(SMALL)
    model = stock(policy_class, MaxNeighbourEnv(), seed=0, policy_kwargs=policy_kwargs, **kwargs, **extra)
    model.learn(40)
    obs, _ = MaxNeighbourEnv().reset(seed=0)
    action, _ = model.predict(obs, deterministic=True)
    n = int(obs["node_mask"].sum())
    assert action.shape == (8,) and np.all(action[n:] == 0)


@pytest.mark.parametrize("name", ALGOS)
def test_save_load_predict(name, tmp_path):
    env = MaxNeighbourEnv()
    model = tiny(name, env=env)
    model.learn(30)
    env.reset(seed=3)
    observations = [env.step(env.action_space.sample())[0] for _ in range(4)]
    before = [model.predict(o, deterministic=True)[0] for o in observations]
    model.save(tmp_path / "model")
    alias, stock, _, _ = ALGOS[name]
    for cls in (alias, stock):
        loaded = cls.load(tmp_path / "model", env=env)
        assert type(loaded.policy) is type(model.policy)
        for o, expected in zip(observations, before):
            np.testing.assert_allclose(loaded.predict(o, deterministic=True)[0], expected, rtol=1e-5, atol=1e-6)
            assert np.all(expected[int(o["node_mask"].sum()) :] == 0)
    loaded.learn(20, reset_num_timesteps=False)  # training goes on


@pytest.mark.parametrize("name", ALGOS)
def test_learns_toy_task_in_a_few_hundred_steps(name):
    alias, _, _, _ = ALGOS[name]
    kwargs = dict(seed=0, gamma=0.0, policy_kwargs=dict(encoder_dim=32, conv_dims=[32, 32]))
    if name == "PPO":
        kwargs.update(n_steps=64, batch_size=32, n_epochs=10, learning_rate=3e-3)
    elif name == "A2C":
        kwargs.update(n_steps=16, learning_rate=1e-3)
    else:
        kwargs.update(learning_starts=100, batch_size=32, learning_rate=1e-3)
    model = alias("GraphPolicy", MaxNeighbourEnv(), **kwargs)
    model.learn(300 if name not in ON_POLICY else 400)
    env = Monitor(MaxNeighbourEnv())
    env.reset(seed=1000)
    learned = evaluate_policy(model, env, n_eval_episodes=20)[0]
    random_return = -4.8  # 8 steps of about -0.6 (tests/test_td3.py measures it)
    # A perfect policy scores 0: demand over a third of the gap closed after a few hundred steps.
    assert learned > 0.65 * random_return, learned


def transitions(count: int, seed: int = 0):
    """Transitions of the toy env, each as (clean, garbage) padded observations and actions: the
    garbage copy has random values in every padded vertex, edge and action slot."""
    env = MaxNeighbourEnv(min_nodes=0)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    obs = env._obs
    out = []
    for _ in range(count):
        action = env.action_space.sample()
        n = int(obs["node_mask"].sum())
        action[n:] = 0.0
        next_obs, reward, _, _, _ = env.step(action)
        out.append((obs, next_obs, action, reward))
        obs = next_obs

    def garbage(o, a):
        o = {k: v.copy() for k, v in o.items()}
        n, e = int(o["node_mask"].sum()), int(o["edge_mask"].sum())
        o["x"][n:] = rng.uniform(-1, 1, o["x"][n:].shape)
        o["edge_index"][:, e:] = rng.integers(0, 8, o["edge_index"][:, e:].shape)
        o["edge_type"][e:] = rng.integers(0, 2, o["edge_type"][e:].shape)
        a = a.copy()
        a[n:] = rng.uniform(-1, 1, a[n:].shape)
        return o, a

    return [((o, no, a, r), (*garbage(o, a)[:1], garbage(no, a)[0], garbage(o, a)[1], r)) for o, no, a, r in out]


def batch(obs_list):
    return {k: np.stack([o[k] for o in obs_list]) for k in obs_list[0]}


def trained_parameters(name: str, data):
    alias, _, _, _ = ALGOS[name]
    if name in ON_POLICY:
        model = tiny(name, env=MaxNeighbourEnv(min_nodes=0), rollout_buffer_class=DictRolloutBuffer)
        buffer = model.rollout_buffer
        for step, (o, _, a, r) in enumerate(data[: buffer.buffer_size]):
            buffer.add(
                batch([o]),
                a[None],
                np.array([r]),
                np.array([step == 0]),
                torch.tensor([[0.1 * step]]),
                torch.tensor([-0.5 * step]),
            )
        buffer.compute_returns_and_advantage(torch.tensor([[0.0]]), np.array([False]))
        model.set_logger(configure(None, []))
        torch.manual_seed(1)
        np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
        model.train()
    else:
        model = tiny(name, env=MaxNeighbourEnv(min_nodes=0), replay_buffer_class=DictReplayBuffer)
        for o, no, a, r in data:
            model.replay_buffer.add(batch([o]), batch([no]), a[None], np.array([r]), np.array([False]), [{}])
        model.set_logger(configure(None, []))
        torch.manual_seed(1)
        np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
        model.train(gradient_steps=3, batch_size=8)
    return model.policy.state_dict()


@pytest.mark.parametrize("name", [n for n in ALGOS if n != "CrossQ"])
def test_padded_slots_never_change_a_loss(name):
    # SB3's padded buffers store whatever sits in padded slots; training on garbage there must give
    # exactly the parameters that training on zeros gives.
    pairs = transitions(24)
    clean = trained_parameters(name, [p[0] for p in pairs])
    garbage = trained_parameters(name, [p[1] for p in pairs])
    for key in clean:
        torch.testing.assert_close(clean[key], garbage[key], msg=key)
    initial = tiny(name).policy.state_dict()
    assert any(not torch.equal(initial[k], clean[k]) for k in clean if initial[k].is_floating_point())


def test_padded_slots_never_change_crossq_critic_or_its_statistics():
    # CrossQ needs the graph buffer (it concatenates observation batches); its critic's batch
    # renormalization must see the real vertices only.
    pairs = transitions(6)
    results = []
    for k in (0, 1):
        policy = tiny("CrossQ").policy
        obs = {key: torch.as_tensor(v).float() for key, v in batch([p[k][0] for p in pairs]).items()}
        actions = torch.as_tensor(np.stack([p[k][2] for p in pairs]))
        policy.critic.set_bn_training_mode(True)
        q = policy.critic(obs, actions)
        stats = [m.ra_mean.clone() for m in policy.critic.modules() if hasattr(m, "ra_mean")]
        results.append((q, stats))
    for a, b in zip(results[0][0] + tuple(results[0][1]), results[1][0] + tuple(results[1][1])):
        torch.testing.assert_close(a, b)


def test_crossq_joint_batch_is_a_disjoint_union():
    model = tiny("CrossQ")
    model.learn(20)
    samples = model.replay_buffer.sample(4)
    joint = torch.cat([samples.observations, samples.next_observations], dim=0)
    assert (
        joint.num_graphs == 8
        and joint.num_nodes == samples.observations.num_nodes + samples.next_observations.num_nodes
    )
    actions = torch.cat([samples.actions, samples.actions])
    critic = model.policy.critic
    critic.set_bn_training_mode(False)
    q_joint = critic(joint, actions)[0]
    torch.testing.assert_close(q_joint[:4], critic(samples.observations, samples.actions)[0])
    torch.testing.assert_close(q_joint[4:], critic(samples.next_observations, samples.actions)[0])


def test_sac_entropy_target_is_minus_one_per_real_vertex():
    model = tiny("SAC")
    assert model.target_entropy == -8.0  # before any batch: SB3's stored value
    model.learn(20)
    assert model.vertex_target_entropy == -1.0
    samples = model.replay_buffer.sample(16)
    model.actor.action_log_prob(samples.observations)
    n_mean = samples.observations.num_nodes / 16
    assert model.target_entropy == pytest.approx(-n_mean)
    assert model.target_entropy == pytest.approx(-n_mean)  # reading has no side effect
    with torch.no_grad():  # the next observations' call (under no_grad in train) records nothing
        model.actor.action_log_prob(model.replay_buffer.sample(16).next_observations)
    assert model.target_entropy == pytest.approx(-n_mean)
    fixed = tiny("SAC", target_entropy=-3.0)
    fixed.actor.action_log_prob(samples.observations)
    assert fixed.vertex_target_entropy is None and fixed.target_entropy == -3.0
    # Stock SB3 keeps -max_nodes.
    stock = stable_baselines3.SAC(GraphSACPolicy, MaxNeighbourEnv(), policy_kwargs=dict(SMALL))
    assert stock.target_entropy == -8.0


@pytest.mark.parametrize("name", ["SAC", "TQC", "CrossQ"])
def test_every_read_of_the_entropy_target_in_train_is_per_vertex(name, monkeypatch):
    # SB3's real `train`: SAC reads target_entropy twice per gradient step (assert and loss), TQC and
    # CrossQ once; every read must be -(mean real vertices of that step's sampled observations).
    model = tiny(name, ent_coef="auto")
    model.learn(30)
    batches, reads = [], []
    sample = model.replay_buffer.sample

    def recording_sample(*args, **kwargs):
        batch = sample(*args, **kwargs)
        batches.append(batch.observations.num_nodes / batch.observations.num_graphs)
        return batch

    getter = type(model).target_entropy.fget

    def counting_getter(self):
        value = getter(self)
        reads.append((len(batches) - 1, value))
        return value

    monkeypatch.setattr(model.replay_buffer, "sample", recording_sample)
    monkeypatch.setattr(type(model), "target_entropy", property(counting_getter, type(model).target_entropy.fset))
    steps = 6
    model.train(gradient_steps=steps, batch_size=8)
    assert len(batches) == steps
    per_step = {"SAC": 2, "TQC": 1, "CrossQ": 1}[name]
    expected_reads = steps * per_step if name != "CrossQ" else per_step * sum(
        1 for k in range(steps) if (model._n_updates - steps + k + 1) % model.policy_delay == 0
    )
    assert len(reads) == expected_reads and expected_reads > 0
    for step, value in reads:
        assert value == pytest.approx(-batches[step]), (step, value, batches)
    assert any(b != 8.0 for b in batches)  # the per-vertex target differs from SB3's -max_nodes


def test_n_steps_go_to_the_graph_buffer_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3 would warn about a buffer class the user never passed
        model = tiny("TD3", n_steps=3, gamma=0.9)
    assert isinstance(model.replay_buffer, GraphReplayBuffer)
    assert (model.replay_buffer.n_steps, model.replay_buffer.gamma) == (3, 0.9)
    model.learn(30)
    discounts = model.replay_buffer.sample(64).discounts.cpu().numpy()  # gamma ** k, k <= 3 steps looked ahead
    assert discounts.shape == (64, 1)
    assert np.isclose(discounts, [[0.9, 0.81, 0.729]]).any(axis=1).all() and np.isclose(discounts, 0.729).any()
    with pytest.warns(UserWarning, match="n_steps=3"):  # an explicit class without n_steps: SB3's warning stands
        tiny("SAC", n_steps=3, replay_buffer_class=GraphReplayBuffer)


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match="gSDE"):
        tiny("SAC", use_sde=True)
    env = MaxNeighbourEnv()
    with pytest.raises(ValueError, match="gSDE"):
        GraphActorCriticPolicy(env.observation_space, env.action_space, lambda _: 1e-3, use_sde=True)
    with pytest.raises(ValueError, match="net_arch"):
        sb3_graph.PPO("GraphPolicy", MaxNeighbourEnv(), policy_kwargs=dict(net_arch=[64]))


@pytest.mark.parametrize("name", ["TD3", "SAC", "PPO"])
def test_vec_normalize_of_graph_observations_is_refused_early(name):
    venv = VecNormalize(DummyVecEnv([MaxNeighbourEnv]), norm_obs=True)
    with pytest.raises(ValueError, match="VecNormalize"):
        tiny(name, env=venv)
    # Reward normalization alone is fine, and so is normalizing no graph entry.
    tiny(name, env=VecNormalize(DummyVecEnv([MaxNeighbourEnv]), norm_obs=False)).learn(20)
    model = tiny(name)
    with pytest.raises(ValueError, match="VecNormalize"):
        model.set_env(VecNormalize(DummyVecEnv([MaxNeighbourEnv]), norm_obs=True))


def test_normalized_masks_are_refused_at_the_policy():
    # Stock SB3 with a padded buffer cannot be checked at construction; the policy stops it.
    policy = tiny("TD3").policy
    obs = {k: torch.as_tensor(v[None]).float() for k, v in MaxNeighbourEnv().reset(seed=0)[0].items()}
    obs["node_mask"] = obs["node_mask"] * 0.7
    with pytest.raises(ValueError, match="VecNormalize"):
        policy.actor(obs)


@pytest.mark.parametrize("name", ["TD3", "SAC", "TQC", "CrossQ", "PPO"])
def test_policy_alone_saves_and_loads(name, tmp_path):
    model = tiny(name)
    policy = model.policy
    policy.save(tmp_path / "policy.pt")
    loaded = type(policy).load(tmp_path / "policy.pt")
    assert loaded.graph_kwargs == policy.graph_kwargs
    obs, _ = MaxNeighbourEnv(min_nodes=3).reset(seed=1)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0])
