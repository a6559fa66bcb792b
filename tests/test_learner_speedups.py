"""What the graph algorithms' ``train`` adds to SB3's for speed (issue #27), with the same updates:
the graph critics leave their own weights out of the policy loss's autograd graph (SB3 discards
those gradients)."""

import copy
import warnings

import numpy as np
import pytest
import stable_baselines3
import torch
from learner_fixtures import SMALL, filled_learner
from sb3_contrib import TQC as ContribTQC

import sb3_graph
from sb3_graph.common.batching import derived_indices
from sb3_graph.common.networks import GraphCritic, constant_parameters, fast_optimizer_kwargs
from sb3_graph.toy_envs import MaxNeighbourEnv

torch.set_num_threads(1)
STOCK = {"TD3": stable_baselines3.TD3, "DDPG": stable_baselines3.DDPG, "SAC": stable_baselines3.SAC, "TQC": ContribTQC}


def trained_state(model, train) -> dict:
    torch.manual_seed(1)
    np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
    derived_indices.clear()
    train(model)
    return {k: v.clone() for k, v in model.policy.state_dict().items()}


@pytest.mark.parametrize("name", ["TD3", "DDPG", "SAC", "TQC"])
def test_updates_equal_those_of_sb3s_train(name):
    """The graph algorithm's ``train`` against SB3's own ``train`` (critic weights in the policy
    loss) on a copy of the same learner: identical weights after the updates, actor and critics."""
    model = filled_learner(name)
    twin = copy.deepcopy(model)
    ours = trained_state(model, lambda m: m.train(gradient_steps=4, batch_size=16))
    stock = trained_state(twin, lambda m: STOCK[name].train(m, gradient_steps=4, batch_size=16))
    assert set(ours) == set(stock)
    for key in ours:
        torch.testing.assert_close(ours[key], stock[key], rtol=0, atol=0, msg=key)
    assert any(not torch.equal(ours[k], v) for k, v in filled_learner(name).policy.state_dict().items())
    # The critic's switch is off again and every parameter trainable.
    assert model.critic.policy_loss_without_weight_gradients is False
    assert all(p.requires_grad for p in model.policy.parameters())


def test_policy_loss_leaves_critic_weight_gradients_out():
    model = filled_learner("TD3")
    critic: GraphCritic = model.critic
    data = model.replay_buffer.sample(16)
    actions = model.actor(data.observations)
    critic.policy_loss_without_weight_gradients = True
    try:
        # Actions with a gradient (a policy loss): no critic weight gradient, the same actor gradient.
        critic.q1_forward(data.observations, actions).mean().backward()
        assert all(p.grad is None for p in critic.parameters())
        frozen_grads = [p.grad.clone() for p in model.actor.parameters()]
        model.actor.zero_grad()
        sum(q.mean() for q in critic(data.observations, model.actor(data.observations))).backward()
        assert all(p.grad is None for p in critic.parameters())
        # Buffer actions (a critic loss): the critic's weights get their gradients.
        sum(q.mean() for q in critic(data.observations, data.actions)).backward()
        assert all(p.grad is not None for p in critic.parameters())
    finally:
        critic.policy_loss_without_weight_gradients = False
    critic.zero_grad()
    model.actor.zero_grad()
    critic.q1_forward(data.observations, model.actor(data.observations)).mean().backward()
    assert all(p.grad is not None for p in critic.q_networks[0].parameters())  # off: SB3's behaviour
    for a, b in zip(frozen_grads, [p.grad for p in model.actor.parameters()], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_constant_parameters_restores_the_flags_after_an_error():
    layer, fixed = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    fixed.bias.requires_grad_(False)
    with pytest.raises(RuntimeError, match="inside"):
        with constant_parameters([layer, fixed]):
            assert not any(p.requires_grad for p in layer.parameters())
            raise RuntimeError("inside")
    assert all(p.requires_grad for p in layer.parameters())
    assert fixed.weight.requires_grad and not fixed.bias.requires_grad  # a frozen parameter stays frozen



@pytest.mark.parametrize("name", ["TD3", "DDPG", "SAC", "TQC"])
def test_graph_policies_default_to_foreach_adam(name):
    """The off-policy graph policies build Adam with ``foreach=True`` (one call per parameter list
    instead of a Python loop per tensor); an explicit choice is kept."""
    model = filled_learner(name)
    for optimizer in (model.actor.optimizer, model.critic.optimizer):
        assert all(group["foreach"] is True for group in optimizer.param_groups)
    chosen = dict(SMALL, optimizer_kwargs=dict(foreach=False, eps=1e-5))
    if name == "TQC":
        chosen["n_quantiles"] = 5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        other = getattr(sb3_graph, name)("GraphPolicy", MaxNeighbourEnv(min_nodes=0), policy_kwargs=chosen)
    assert other.critic.optimizer.param_groups[0]["foreach"] is False
    assert other.critic.optimizer.param_groups[0]["eps"] == 1e-5


def test_fast_optimizer_kwargs():
    assert fast_optimizer_kwargs(torch.optim.Adam, None) == {"foreach": True}
    assert fast_optimizer_kwargs(torch.optim.AdamW, {"eps": 1e-5}) == {"eps": 1e-5, "foreach": True}
    given = {"fused": True}
    assert fast_optimizer_kwargs(torch.optim.Adam, given) == {"fused": True} and given == {"fused": True}
    assert fast_optimizer_kwargs(torch.optim.Adam, {"differentiable": True}) == {"differentiable": True}
    assert fast_optimizer_kwargs(torch.optim.SGD, None) == {}


@pytest.mark.parametrize("name", ["TD3", "SAC"])
def test_foreach_adam_updates_equal_per_tensor_adam(name):
    """``foreach`` Adam makes the same updates as the per-tensor loop that torch picks on CPU
    otherwise (and the learner used before): identical weights after a few gradient steps."""
    model = filled_learner(name)
    twin = copy.deepcopy(model)
    for optimizer in (twin.actor.optimizer, twin.critic.optimizer):
        for group in optimizer.param_groups:
            group["foreach"] = False
    ours = trained_state(model, lambda m: m.train(gradient_steps=4, batch_size=16))
    per_tensor = trained_state(twin, lambda m: m.train(gradient_steps=4, batch_size=16))
    for key in ours:
        torch.testing.assert_close(ours[key], per_tensor[key], rtol=0, atol=0, msg=key)
