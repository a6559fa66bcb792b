"""Behaviour cloning (sb3_graph.behaviour_clone), the masked imitation loss and the bc_coef regularizer."""

import warnings

import numpy as np
import pytest
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

import sb3_graph
from sb3_graph.common.buffers import GraphReplayBuffer, GraphRolloutBuffer
from sb3_graph.common.demonstrations import demonstration_loss, expert_targets, parse_bc_coef
from sb3_graph.toy_envs import MaxNeighbourEnv, max_neighbour_expert

SMALL = dict(encoder_dim=16, conv_dims=[16, 16])
OFF_POLICY = ("TD3", "DDPG", "SAC", "TQC", "CrossQ")


def learner(name, env=None, **kwargs):
    env = MaxNeighbourEnv(min_nodes=0) if env is None else env
    policy_kwargs = dict(SMALL, n_quantiles=5) if name == "TQC" else dict(SMALL)
    extra = dict(n_steps=16, batch_size=8) if name == "PPO" else dict(n_steps=16) if name == "A2C" else {}
    if name in OFF_POLICY:
        extra = dict(learning_starts=0, batch_size=16, buffer_size=200)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = getattr(sb3_graph, name)("GraphPolicy", env, seed=0, policy_kwargs=policy_kwargs, **extra, **kwargs)
    model.set_logger(configure(None, []))
    return model


def toy_transitions(count, seed=0):
    env = MaxNeighbourEnv(min_nodes=0)
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    out = []
    for _ in range(count):
        action = env.action_space.sample() * obs["node_mask"]
        next_obs, reward, _, _, _ = env.step(action)
        batched = {k: v[None] for k, v in obs.items()}
        out.append((obs, next_obs, action, reward, max_neighbour_expert(batched)[0]))
        obs = next_obs
    return out


def with_garbage(obs, labels, rng):
    """Random values in every padded vertex, edge and label slot."""
    obs = {k: v.copy() for k, v in obs.items()}
    n, e = int(obs["node_mask"].sum()), int(obs["edge_mask"].sum())
    obs["x"][n:] = rng.uniform(-1, 1, obs["x"][n:].shape)
    obs["edge_index"][:, e:] = rng.integers(0, 8, obs["edge_index"][:, e:].shape)
    obs["edge_type"][e:] = rng.integers(0, 2, obs["edge_type"][e:].shape)
    labels = labels.copy()
    labels[n:] = rng.uniform(-1, 1, labels[n:].shape)
    return obs, labels


def stack(o):
    return {k: v[None] for k, v in o.items()}


def fill(buffer, data, garbage=False, labelled=True):
    rng = np.random.default_rng(1)
    for obs, next_obs, action, reward, labels in data:
        if garbage:
            obs, labels = with_garbage(obs, labels, rng)
        buffer.add(stack(obs), stack(next_obs), action[None], [reward], [False], [{}],
                   expert_action=labels[None] if labelled else None)  # fmt: skip


# ------------------------------------------------------------------ the masked loss
@pytest.mark.parametrize("name", ["TD3", "SAC", "PPO"])
def test_padded_slots_never_enter_the_imitation_loss(name):
    model = learner(name)
    data = toy_transitions(24)
    losses, grads = [], []
    for garbage in (False, True):
        buffer = GraphReplayBuffer(64, model.observation_space, model.action_space, store_expert_actions=True)
        fill(buffer, data, garbage=garbage)
        np.random.seed(3)  # noqa: NPY002
        samples = buffer.sample(16)
        if garbage:  # and garbage in the padded slots of the sampled labels themselves
            padded = torch.arange(samples.expert_actions.shape[1])[None] >= torch.as_tensor(
                np.bincount(samples.observations.batch.numpy(), minlength=16)
            )[:, None]
            samples = samples._replace(expert_actions=torch.where(padded, torch.rand_like(samples.expert_actions),
                                                                  samples.expert_actions))  # fmt: skip
        model.policy.zero_grad()
        loss = demonstration_loss(model.policy, samples)
        loss.backward()
        losses.append(loss.detach())
        grads.append([p.grad.clone() for p in model.policy.parameters() if p.grad is not None])
    assert torch.equal(losses[0], losses[1])
    for clean, noisy in zip(*grads, strict=True):
        torch.testing.assert_close(clean, noisy)
    # a real vertex's label does enter it
    real = samples.observations
    changed = samples.expert_actions.clone()
    changed[real.batch[0], real.node_slot[0]] += 0.5
    assert not torch.equal(demonstration_loss(model.policy, samples._replace(expert_actions=changed)), losses[1])


def test_unlabelled_transitions_never_enter_the_imitation_loss():
    model = learner("TD3")
    data = toy_transitions(16)
    buffer = GraphReplayBuffer(64, model.observation_space, model.action_space, store_expert_actions=True)
    fill(buffer, data[:8], labelled=True)
    fill(buffer, data[8:], labelled=False)
    assert buffer.num_expert_transitions == 8
    np.random.seed(0)  # noqa: NPY002
    expert_only = buffer.sample_expert(64)
    assert bool(expert_only.expert_mask.all())
    mixed = buffer.sample(64)
    assert not bool(mixed.expert_mask.all()) and bool(mixed.expert_mask.any())
    # the unlabelled graphs' zero labels do not count: relabelling them changes nothing
    unlabelled = ~mixed.expert_mask
    noisy = mixed.expert_actions.clone()
    noisy[unlabelled] = 0.7
    assert torch.equal(demonstration_loss(model.policy, mixed),
                       demonstration_loss(model.policy, mixed._replace(expert_actions=noisy)))  # fmt: skip


def test_rollout_buffer_labels_reach_the_minibatches_of_their_states():
    env = MaxNeighbourEnv(min_nodes=0)
    space = env.observation_space
    buffer = GraphRolloutBuffer(6, space, env.action_space, n_envs=1)
    data = toy_transitions(6)
    for step, (obs, _, action, reward, labels) in enumerate(data):
        buffer.label_step(step, labels[None])
        buffer.add(stack(obs), action[None], np.array([reward]), np.array([step == 0]),
                   torch.zeros(1, 1), torch.zeros(1))  # fmt: skip
    buffer.compute_returns_and_advantage(torch.zeros(1, 1), np.array([False]))
    (samples,) = list(buffer.get(6))
    graphs = samples.observations
    for b in range(6):
        # find the transition by its vertex features, then compare its labels
        x = graphs.x[graphs.batch == b]
        k = next(i for i, d in enumerate(data) if int(d[0]["node_mask"].sum()) == len(x)
                 and np.allclose(d[0]["x"][: len(x)], x.numpy()))  # fmt: skip
        n = len(x)
        np.testing.assert_array_equal(samples.expert_actions[b, :n].numpy(), data[k][4][:n])
    assert bool(samples.expert_mask.all())


def test_expert_targets_are_in_the_policy_units():
    td3, ppo = learner("TD3"), learner("PPO")
    actions = np.array([[2.0, -0.5, 0.25, 0, 0, 0, 0, 0]], np.float32)
    np.testing.assert_allclose(expert_targets(td3.policy, actions)[0, :3], [1.0, -0.5, 0.25])  # bounds [-1, 1]
    np.testing.assert_allclose(expert_targets(ppo.policy, actions)[0, :3], [1.0, -0.5, 0.25])


# ------------------------------------------------------------------ bc_coef
def trained_state(name, bc_coef, labelled):
    model = learner(name, bc_coef=bc_coef)
    data = toy_transitions(48)
    if labelled:
        model.replay_buffer.enable_expert_actions()
    fill(model.replay_buffer, data, labelled=labelled)
    torch.manual_seed(1)
    np.random.seed(1)  # noqa: NPY002
    model.train(gradient_steps=4, batch_size=16)
    return {k: v.clone() for k, v in model.policy.state_dict().items()}


@pytest.mark.parametrize("name", OFF_POLICY)
def test_bc_coef_zero_leaves_the_updates_bit_for_bit(name):
    today = trained_state(name, 0.0, labelled=False)
    zero = trained_state(name, 0.0, labelled=True)  # demonstrations in the buffer, coefficient 0
    assert set(today) == set(zero)
    for key in today:
        assert torch.equal(today[key], zero[key]), key
    regularized = trained_state(name, 1.0, labelled=True)
    actor = [k for k in today if k.startswith("actor.") and today[k].is_floating_point()]
    assert any(not torch.equal(today[k], regularized[k]) for k in actor)


@pytest.mark.parametrize("name", ["PPO", "A2C"])
def test_on_policy_bc_coef_zero_leaves_the_updates_bit_for_bit(name):
    states, losses = [], []
    expert = max_neighbour_expert
    for kwargs in ({}, {"bc_coef": 0.0, "bc_expert": expert}, {"bc_coef": 1.0, "bc_expert": expert}):
        env = make_vec_env(MaxNeighbourEnv, n_envs=1, seed=0, env_kwargs={"min_nodes": 0})
        model = learner(name, env=env, **kwargs)
        model.learn(16)
        states.append({k: v.clone() for k, v in model.policy.state_dict().items()})
        losses.append(model.logger.name_to_value.get("train/bc_loss"))
    for key in states[0]:
        assert torch.equal(states[0][key], states[1][key]), key
    assert any(not torch.equal(states[0][k], states[2][k]) for k in states[0] if states[0][k].is_floating_point())


def test_on_policy_bc_coef_needs_an_expert():
    env = make_vec_env(MaxNeighbourEnv, n_envs=1, seed=0)
    model = learner("PPO", env=env, bc_coef=0.5)
    with pytest.raises(ValueError, match="bc_expert"):
        model.learn(16)


def test_bc_coef_schedule_and_bad_values():
    assert parse_bc_coef(0.5) == 0.5 and parse_bc_coef("lin_2") == "lin_2"
    model = learner("TD3", bc_coef="lin_2")
    model._current_progress_remaining = 0.25
    assert model.bc_coefficient() == pytest.approx(0.5)
    for bad in (-1, "lin_x", "fast", float("nan"), True):
        with pytest.raises(ValueError, match="bc_coef"):
            learner("TD3", bc_coef=bad)


# ------------------------------------------------------------------ cloning end to end
def toy_error(model, steps=150):
    env = MaxNeighbourEnv()
    obs, _ = env.reset(seed=123)
    errors = []
    for _ in range(steps):
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, *_ = env.step(action)
        errors.append(-reward)
    return float(np.mean(errors))


@pytest.mark.parametrize("name", ["TD3", "SAC"])
def test_cloned_policy_acts_like_the_toy_expert(name):
    torch.set_num_threads(1)
    env = make_vec_env(MaxNeighbourEnv, n_envs=2, seed=0)
    model = learner(name, env=env, bc_coef=0.0)
    model.replay_buffer_kwargs = {}
    before = toy_error(model)
    result = sb3_graph.behaviour_clone(model, max_neighbour_expert, transitions=400, gradient_steps=250,
                                       batch_size=64, critic_steps=10, learning_rate=1e-3)  # fmt: skip
    after = toy_error(model)
    assert len(result["actor_loss"]) == 250 and len(result["critic_loss"]) == 10
    assert result["transitions"] == 400 and result["expert_share"] == 1.0
    assert model.replay_buffer.num_expert_transitions == 200  # 200 steps of 2 sub-environments
    assert result["actor_loss"][-1] < 0.2 * result["actor_loss"][0]
    assert after < 0.25 * before, (before, after)
    assert after < 0.08  # a uniformly random policy: ~0.6
    if name == "TD3":  # the actor target is the cloned actor (to rounding: the warm-up's polyak updates)
        for a, t in zip(model.actor.parameters(), model.actor_target.parameters(), strict=True):
            torch.testing.assert_close(a, t)


def test_dagger_mixes_in_the_policy_and_sets_the_on_policy_expert():
    env = make_vec_env(MaxNeighbourEnv, n_envs=2, seed=0)
    model = learner("PPO", env=env)
    result = sb3_graph.behaviour_clone(model, max_neighbour_expert, transitions=200, gradient_steps=20,
                                       batch_size=32, beta=lambda k: 1.0 if k == 0 else 0.0, rounds=2)  # fmt: skip
    assert result["expert_share"] == pytest.approx(0.5)
    assert len(result["actor_loss"]) == 20 and result["critic_loss"] == []
    assert model.bc_expert is max_neighbour_expert


def test_behaviour_clone_bad_arguments():
    env = make_vec_env(MaxNeighbourEnv, n_envs=1, seed=0)
    model = learner("TD3", env=env)
    with pytest.raises(ValueError, match="transitions"):
        sb3_graph.behaviour_clone(model, max_neighbour_expert, transitions=0, gradient_steps=1)
    with pytest.raises(ValueError, match="expert: expected actions of shape"):
        sb3_graph.behaviour_clone(model, lambda obs: np.zeros((1, 3)), transitions=4, gradient_steps=1)
    with pytest.raises(ValueError, match="beta"):
        sb3_graph.behaviour_clone(model, max_neighbour_expert, transitions=4, gradient_steps=1, beta=2.0)


def test_experiment_keys_of_cloning():
    from sb3_graph.files.experiment_files import ExperimentError, build_algorithm_kwargs, check_entry

    entry = {"n_timesteps": 10, "pretrain_from": "aim", "pretrain_transitions": 100, "pretrain_steps": 20,
             "bc_coef": "lin_0.5"}  # fmt: skip
    kwargs = build_algorithm_kwargs(entry, 8)
    assert kwargs == {"bc_coef": "lin_0.5"}  # the pretrain_* keys are the trainer's
    for key, bad in (("pretrain_steps", -1), ("pretrain_transitions", 0), ("bc_coef", "fast"), ("pretrain_from", "")):
        with pytest.raises(ExperimentError, match=key):
            check_entry({"n_timesteps": 10, key: bad})


def _fields(samples):
    out = {}
    for name, value in samples._asdict().items():
        if isinstance(value, dict):
            out.update({f"{name}.{k}": v for k, v in value.items()})
        elif isinstance(value, torch.Tensor):
            out[name] = value
    return out


def test_recorded_demonstrations_replay_into_another_model_as_collected():
    import io

    def refuse(obs):
        raise AssertionError("a replay must not ask the expert")

    env = make_vec_env(MaxNeighbourEnv, n_envs=2, seed=0)
    first = learner("TD3", env=env)
    result = sb3_graph.behaviour_clone(first, max_neighbour_expert, transitions=60, gradient_steps=2, batch_size=8,
                                       critic_steps=0, record=True)  # fmt: skip
    demos = result["demonstrations"]
    assert demos.transitions == 60 and demos.expert_steps == 60 and demos.arrays()["dones"].any()
    file = io.BytesIO()
    demos.save(file)
    file.seek(0)
    loaded = sb3_graph.Demonstrations.load(file)
    second = learner("TD3", env=make_vec_env(MaxNeighbourEnv, n_envs=2, seed=5))
    again = sb3_graph.behaviour_clone(second, refuse, transitions=1, gradient_steps=2, batch_size=8, critic_steps=0,
                                      demonstrations=loaded)  # fmt: skip
    assert again["transitions"] == 60 and again["expert_share"] == 1.0
    a, b = first.replay_buffer, second.replay_buffer
    assert a.pos == b.pos == 30 and b.num_expert_transitions == 60
    np.testing.assert_array_equal(a.rewards, b.rewards)
    np.testing.assert_array_equal(a.dones, b.dones)
    np.random.seed(3)  # noqa: NPY002 (SB3 buffers sample with the legacy global generator)
    one = _fields(a.sample_expert(16))
    np.random.seed(3)  # noqa: NPY002 (SB3 buffers sample with the legacy global generator)
    two = _fields(b.sample_expert(16))
    assert one.keys() == two.keys()
    for name in one:
        torch.testing.assert_close(one[name], two[name], rtol=0, atol=0, msg=name)
    with pytest.raises(ValueError, match="do not fit"):
        sb3_graph.behaviour_clone(learner("TD3", env=make_vec_env(MaxNeighbourEnv, n_envs=1, seed=0)), refuse,
                                  transitions=1, gradient_steps=0, demonstrations=loaded)  # fmt: skip
    with pytest.raises(ValueError, match="not a demonstrations file"):
        sb3_graph.Demonstrations.load(io.BytesIO(b"nonsense"))
