"""Shared pieces of the sb3_graph benchmarks: a paper-scale graph env, buffer filling, timing, tables."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from sb3_graph import GraphSpace

MAX_NODES, NODE_FEATURES, MAX_EDGES, NUM_RELATIONS = 64, 3, 1024, 2


class PaperScaleGraphEnv(gym.Env):
    """Random graphs at the paper's scale: ~20 vertices (15..25) and ~3 edges per vertex, in a
    ``GraphSpace(max_nodes=64, max_edges=1024)``.

    :param mean_nodes: mean vertex count
    :param edges_per_node: edges per vertex
    """

    def __init__(self, mean_nodes: int = 20, edges_per_node: int = 3) -> None:
        self.mean_nodes = mean_nodes
        self.edges_per_node = edges_per_node
        self.observation_space = GraphSpace(MAX_NODES, NODE_FEATURES, MAX_EDGES, NUM_RELATIONS)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (MAX_NODES,), np.float32)

    def graph(self) -> dict[str, np.ndarray]:
        rng = self.np_random
        n = int(rng.integers(self.mean_nodes - 5, self.mean_nodes + 6))
        e = self.edges_per_node * n
        src = rng.integers(0, n, e)
        dst = (src + rng.integers(1, n, e)) % n
        x = rng.standard_normal((n, NODE_FEATURES)).astype(np.float32)
        return self.observation_space.encode(x, np.stack([src, dst]), rng.integers(0, NUM_RELATIONS, e))

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        return self.graph(), {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        return self.graph(), float(self.np_random.standard_normal()), False, False, {}


def fill(
    buffers: list[Any],
    env: PaperScaleGraphEnv,
    count: int,
    transform: Callable | None = None,
    episode_length: int = 100,
) -> None:
    """Add ``count`` random transitions (n_envs=1) to every buffer, as SB3 does: the next observation
    is the following observation, except at the end of each ``episode_length``-step episode.

    :param transform: maps an observation to what a buffer stores (e.g. flattening for MlpPolicy)
    """
    env.reset(seed=0)
    obs = env.graph()
    for step in range(count):
        next_obs = env.graph()
        done = step % episode_length == episode_length - 1
        action = env.np_random.uniform(-1, 1, (1, MAX_NODES)).astype(np.float32)
        reward = np.array([env.np_random.standard_normal()])
        for buffer in buffers:
            o, n = (transform(obs), transform(next_obs)) if transform else (obs, next_obs)
            if isinstance(o, dict):
                o, n = {k: v[None] for k, v in o.items()}, {k: v[None] for k, v in n.items()}
            else:
                o, n = o[None], n[None]
            buffer.add(o, n, action, reward, np.array([done]), [{}])
        obs = env.graph() if done else next_obs


def rate(function: Callable[[], Any], min_seconds: float = 1.0, repeats: int = 3) -> float:
    """Calls per second of ``function``: best of ``repeats`` runs of at least ``min_seconds`` each
    (best-of damps the noise of other processes on a shared machine)."""
    function()  # warm-up
    best = 0.0
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < min_seconds:
            function()
            calls += 1
        best = max(best, calls / elapsed)
    return best


def interleaved_rates(
    functions: list[Callable[[], Any]],
    min_seconds: float = 1.0,
    repeats: int = 3,
    clock: Callable[[], float] = time.perf_counter,
) -> list[float]:
    """Calls per second of each function, best of ``repeats`` runs, the functions taking turns run by
    run: on a machine shared with other work, a load change then hits all of them alike instead
    of whichever happened to run at the time. ``clock``: ``time.perf_counter`` (wall) or
    ``time.process_time`` (CPU time of this process: on a loaded machine, the time the process
    was not scheduled does not count)."""
    for function in functions:
        function()  # warm-up
    best = [0.0] * len(functions)
    for _ in range(repeats):
        for k, function in enumerate(functions):
            calls, start = 0, clock()
            while (elapsed := clock() - start) < min_seconds:
                function()
                calls += 1
            best[k] = max(best[k], calls / elapsed)
    return best


def graph_td3_steps_per_second(threads: int, min_seconds: float = 1.5, fill_count: int = 2000) -> float:
    """TD3 gradient steps per second (batch 256) with GraphPolicy + GraphReplayBuffer."""
    from sb3_graph import TD3

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        env = PaperScaleGraphEnv()
        model = TD3("GraphPolicy", env, buffer_size=fill_count, batch_size=256, seed=0)
        model.set_logger(_null_logger())
        fill([model.replay_buffer], env, fill_count)
        return rate(lambda: model.train(gradient_steps=2, batch_size=256), min_seconds) * 2
    finally:
        torch.set_num_threads(previous)


def threads_table(min_seconds: float = 1.5) -> str:
    """Markdown rows: graph learner steps/s with 1 and 2 torch threads."""
    one = graph_td3_steps_per_second(1, min_seconds)
    two = graph_td3_steps_per_second(2, min_seconds)
    return markdown_table(
        ["torch threads", "TD3 GraphPolicy gradient steps/s (batch 256)", "ratio vs 1 thread"],
        [["1", f"{one:.1f}", "1.00"], ["2", f"{two:.1f}", f"{two / one:.2f}"]],
    )


@contextlib.contextmanager
def per_tensor_optimizers(model: Any) -> Iterator[None]:
    """Within the block, the optimizers of ``model``'s policy run torch's per-tensor loop (as before
    issue #27, when the graph policies did not default to ``foreach=True``): the same updates,
    slower."""
    groups = [g for optimizer in (model.actor.optimizer, model.critic.optimizer) for g in optimizer.param_groups]
    previous = [g.get("foreach") for g in groups]
    for group in groups:
        group["foreach"] = False
    try:
        yield
    finally:
        for group, value in zip(groups, previous):
            group["foreach"] = value


def _null_logger():
    from stable_baselines3.common.logger import configure

    return configure(folder=None, format_strings=[])


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def machine_line() -> str:
    command = "python " + " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:])
    return f"machine: nproc={os.cpu_count()}, torch {torch.__version__}; command: `{command}`"


#: The recordings of the benchmarks: a training config and the planner that drives it.
RECORDINGS = {
    # The paper's reward and observation (td3_fair.yml), driven by its retrained planner.
    "fair": ("zoo_configs/td3_fair.yml", "envs/pretrained/coop_4way_fair/best_model.safetensors"),
    # The shipped planner's config: a residual over full throttle behind the shield, with vertex and
    # edge features, driven by the shipped planner's own corrections.
    "features": (
        "zoo_configs/td3_residual_features.yml",
        "envs/pretrained/coop_4way_residual/best_model.safetensors",
    ),
}


class IntersectionRecording:
    """Transitions of the intersection environment as a training config trains on it
    (``CoopIntersection4Way-v0`` with the config's ``env_kwargs``, read from the file; ``fair``:
    ``zoo_configs/td3_fair.yml``: 60 s episodes, spawn probability drawn from [0.01, 0.07], blocked
    spawns dropped, a collision ends the episode), driven by a pretrained planner with Gaussian
    action noise (0.1); a residual planner drives with its correction, the action of a residual
    environment. ``fair``: about 15 vehicles and 62 edges per observation, in
    ``GraphSpace(max_nodes=64, max_edges=1024)``.

    :param count: transitions to record
    :param seed: seed of the environment and of the noise
    :param recording: a key of :data:`RECORDINGS`
    """

    ENV_ID = "CoopIntersection4Way-v0"

    def __init__(self, count: int, seed: int = 0, recording: str = "fair") -> None:
        import envs  # noqa: F401 - registers the environments
        from envs.planners import make_planner
        from sb3_graph.files.experiment_files import read_experiment

        root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
        # The config's own env_kwargs, not a copy: its traffic settings (e.g. spawn_queue: 0, blocked
        # spawns dropped, against the environment's default queue of 10) set the graph sizes.
        config, model = RECORDINGS[recording]
        env_kwargs = read_experiment(os.path.join(root, config), self.ENV_ID).get("env_kwargs") or {}
        env = gym.make(self.ENV_ID, **env_kwargs)
        planner = make_planner(os.path.join(root, model))
        planner = getattr(planner, "correction", planner)  # a residual environment's action
        base = env.unwrapped
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        self.observation_space, self.action_space = env.observation_space, env.action_space
        self.transitions: list[tuple[dict, dict, np.ndarray, float, bool]] = []
        while len(self.transitions) < count:
            action = base.accelerations_to_action(np.asarray(planner.act(base.scene()), dtype=float))
            action = np.clip(action + rng.normal(0.0, 0.1, action.shape), -1, 1).astype(np.float32)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            self.transitions.append((obs, next_obs, action, float(reward), bool(terminated or truncated)))
            obs = env.reset()[0] if terminated or truncated else next_obs
        env.close()

    def env(self) -> gym.Env:
        """An environment with the recording's spaces whose observations replay the recording."""
        return _ReplayEnv(self)

    def fill(self, buffers: list[Any], transform: Callable | None = None) -> None:
        """Add every transition (n_envs=1) to every buffer.

        :param transform: maps an observation to what a buffer stores (e.g. flattening for MlpPolicy)
        """
        for obs, next_obs, action, reward, done in self.transitions:
            for buffer in buffers:
                o, n = (transform(obs), transform(next_obs)) if transform else (obs, next_obs)
                if isinstance(o, dict):
                    o, n = {k: v[None] for k, v in o.items()}, {k: v[None] for k, v in n.items()}
                else:
                    o, n = o[None], n[None]
                buffer.add(o, n, action[None], np.array([reward]), np.array([done]), [{"TimeLimit.truncated": False}])

    def mean_size(self) -> tuple[float, float]:
        """Mean vertices and edges per observation."""
        nodes = np.mean([t[0]["node_mask"].sum() for t in self.transitions])
        edges = np.mean([t[0]["edge_mask"].sum() for t in self.transitions])
        return float(nodes), float(edges)


class _ReplayEnv(gym.Env):
    """The spaces of a recording; ``reset``/``step`` return its observations in order (for
    building learners and filling rollouts)."""

    def __init__(self, recording: IntersectionRecording) -> None:
        self.recording = recording
        self.observation_space, self.action_space = recording.observation_space, recording.action_space
        self._next = 0

    def graph(self) -> dict[str, np.ndarray]:
        obs = self.recording.transitions[self._next % len(self.recording.transitions)][0]
        self._next += 1
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self._next = 0
        return self.graph(), {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        return self.graph(), 0.0, False, False, {}
