"""Record (or check) the parameters of every graph learner after a few gradient steps.

The fixture ``tests/data/learner_updates.safetensors`` holds, per algorithm (TD3, DDPG, SAC, TQC,
CrossQ, PPO, A2C with small graph networks on ``GraphMaxNeighbour``): the policy's parameters
before training and after training on fixed transitions (off-policy: 3 gradient steps of batch 8
from the graph replay buffer; on-policy: one ``train`` call over a fixed rollout), keyed
``"<algorithm>/initial/<parameter>"`` and ``"<algorithm>/trained/<parameter>"``.
``tests/test_learner_updates.py`` loads the initial parameters into a fresh learner (so the
state_dict keys of the recording must still load), trains it on the same transitions with the
code under test and compares the trained parameters.

The committed fixture was recorded with the learner before issue #27 (commit 849ee98), so the test
proves that the faster layers and policies make the same updates.

Run: ``python scripts/record_learner_updates.py [--out PATH]``, or ``--check`` to print the largest
difference between the code here and the fixture.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from stable_baselines3.common.logger import configure

import sb3_graph
from sb3_graph.toy_envs import MaxNeighbourEnv

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "learner_updates.safetensors"
ALGORITHMS = ("TD3", "DDPG", "SAC", "TQC", "CrossQ", "PPO", "A2C")
ON_POLICY = ("PPO", "A2C")
SMALL = dict(encoder_dim=16, conv_dims=[16, 16])


def make_learner(name: str):
    """A small graph learner of ``name`` on the toy task (seed 0)."""
    policy_kwargs = dict(SMALL, n_quantiles=5) if name == "TQC" else dict(SMALL)
    if name in ON_POLICY:
        kwargs = dict(n_steps=16, batch_size=8, n_epochs=2) if name == "PPO" else dict(n_steps=16)
    else:
        kwargs = dict(learning_starts=0, batch_size=8, buffer_size=200)
    env = MaxNeighbourEnv(min_nodes=0)
    model = getattr(sb3_graph, name)("GraphPolicy", env, seed=0, policy_kwargs=policy_kwargs, **kwargs)
    model.set_logger(configure(None, []))
    return model


def transitions(count: int = 40, seed: int = 0) -> list:
    """Fixed transitions of the toy task (random actions, 0 in padded slots)."""
    env = MaxNeighbourEnv(min_nodes=0)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32) * obs["node_mask"]
        next_obs, reward, terminated, truncated, _ = env.step(action)
        out.append((obs, next_obs, action, float(reward), bool(terminated or truncated)))
        obs = env.reset()[0] if terminated or truncated else next_obs
    return out


def train(model, data: list) -> None:
    """Train ``model`` on ``data`` as the fixture does (fixed seeds for the sampling)."""
    name = type(model).__name__
    stack = lambda o: {k: v[None] for k, v in o.items()}  # noqa: E731
    if name in ON_POLICY:
        buffer = model.rollout_buffer
        for step, (o, _, a, r, _done) in enumerate(data[: buffer.buffer_size]):
            buffer.add(stack(o), a[None], np.array([r]), np.array([step == 0]), torch.tensor([[0.1 * step]]),
                       torch.tensor([-0.5 * step]))  # fmt: skip
        buffer.compute_returns_and_advantage(torch.tensor([[0.0]]), np.array([False]))
        torch.manual_seed(1)
        np.random.seed(1)  # noqa: NPY002 (SB3 samples with the global generator)
        model.train()
        return
    for o, no, a, r, done in data:
        model.replay_buffer.add(stack(o), stack(no), a[None], np.array([r]), np.array([done]), [{}])
    torch.manual_seed(1)
    np.random.seed(1)  # noqa: NPY002
    model.train(gradient_steps=3, batch_size=8)


def record() -> dict[str, torch.Tensor]:
    tensors = {}
    data = transitions()
    for name in ALGORITHMS:
        model = make_learner(name)
        for key, value in model.policy.state_dict().items():
            tensors[f"{name}/initial/{key}"] = value.detach().clone().contiguous()
        train(model, data)
        for key, value in model.policy.state_dict().items():
            tensors[f"{name}/trained/{key}"] = value.detach().clone().contiguous()
    return tensors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--check", action="store_true", help="compare with the fixture instead of writing it")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tensors = record()
    if not args.check:
        save_file(tensors, str(args.out))
        print(f"wrote {len(tensors)} tensors to {args.out}")
        return
    fixture = load_file(str(args.out))
    for key in sorted(set(fixture) | set(tensors)):
        if key not in fixture or key not in tensors:
            print(f"{key}: only in {'fixture' if key in fixture else 'this code'}")
        elif fixture[key].is_floating_point():
            print(f"{key}: largest difference {float((fixture[key] - tensors[key]).abs().max()):.3g}")


if __name__ == "__main__":
    main()
