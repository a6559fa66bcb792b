"""Replay and rollout buffers that store only the real vertices and edges of each graph observation.

SB3's ``DictReplayBuffer`` stores every observation at its padded size (``max_nodes`` vertices,
``max_edges`` edges), ~28 kB per transition for ``max_nodes=64, max_edges=1024``. Here each
field lives in a flat *pool* of rows (one row per real vertex or edge) and each transition keeps
``(start, count)`` into it. Within an episode a transition's next observation is the following
transition's observation (SB3 adds them so), and it is then stored once. For graphs of ~20
vertices and ~60 edges this comes to ~0.7 kB per transition (~1.3 kB when every step ends an
episode).

Transitions keep SB3's ``(buffer_size, n_envs)`` ring with its exact FIFO semantics. Because the
ring frees transitions in the order it wrote them, each pool is itself a circular buffer of rows:
after the ring wraps, new rows reuse the space of the overwritten ones and nothing is copied.
While the ring fills, a pool grows geometrically (compacting the live rows into the new array);
when the ring first wraps, it shrinks to the live rows plus a small slack; it grows again only if
the graphs grow.

:class:`GraphRolloutBuffer` (PPO, A2C) keeps each step's real rows and joins them once per rollout;
minibatches are sets of graphs, each batch one disjoint graph.

Both buffers check what they store (vectorized): real vertices in the leading slots, every real edge
between real vertices of its own graph, relation ids in ``[0, num_relations)``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, ReplayBuffer, RolloutBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples, RolloutBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_graph.common.algorithm import check_vec_normalize
from sb3_graph.common.batching import GraphBatch
from sb3_graph.common.spaces import EDGE_ATTR, EDGE_INDEX, EDGE_MASK, EDGE_TYPE, NODE_MASK, X, edge_dims, graph_dims


class ExpertReplayBufferSamples(NamedTuple):
    """SB3's ``ReplayBufferSamples`` (same first fields, in the same order) plus the demonstrations'
    labels: what :class:`GraphReplayBuffer` returns when it stores expert actions.

    :param expert_actions: ``(B, max_nodes)`` expert action per vertex slot, in the units of
        ``actions`` (0 in padded slots and for unlabelled transitions)
    :param expert_mask: ``(B,)`` bool, the transitions that carry an expert action
    """

    observations: Any
    actions: torch.Tensor
    next_observations: Any
    dones: torch.Tensor
    rewards: torch.Tensor
    discounts: torch.Tensor | None
    expert_actions: torch.Tensor
    expert_mask: torch.Tensor


class ExpertRolloutBufferSamples(NamedTuple):
    """SB3's ``RolloutBufferSamples`` plus the expert's labels of the rollout states (see
    :meth:`GraphRolloutBuffer.label_step`); fields as in :class:`ExpertReplayBufferSamples`."""

    observations: Any
    actions: torch.Tensor
    old_values: torch.Tensor
    old_log_prob: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor
    expert_actions: torch.Tensor
    expert_mask: torch.Tensor


def _exclusive_cumsum(counts: np.ndarray) -> np.ndarray:
    offsets = np.zeros(len(counts), dtype=np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    return offsets


def _segment_indices(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated ``range(start, start + count)`` of every segment, without a Python loop.

    :return: the flat indices and each segment's offset in them
    """
    counts = counts.astype(np.int64, copy=False)
    offsets = _exclusive_cumsum(counts)
    total = int(offsets[-1] + counts[-1]) if len(counts) else 0
    indices = np.repeat(starts.astype(np.int64, copy=False) - offsets, counts) + np.arange(
        total, dtype=np.int64
    )
    return indices, offsets


def split_graphs(
    obs: dict[str, np.ndarray], n_envs: int, max_nodes: int, node_features: int, num_relations: int, owner: str
) -> tuple[dict, np.ndarray, dict, np.ndarray, np.ndarray]:
    """Real vertex rows and edge rows of ``n_envs`` padded observations, checked (vectorized).

    :param obs: padded observations with leading dimension ``n_envs``
    :param n_envs: number of graphs
    :param max_nodes: vertex slots per graph
    :param node_features: features per vertex
    :param num_relations: number of relations
    :param owner: class name for the error messages
    :return: vertex rows ``{"x"}``, vertex counts, edge rows ``{"src", "dst", "type"[, "attr"]}``
        (local vertex ids), edge counts and the ``(n_envs, max_nodes)`` boolean vertex mask
    :raises ValueError: when real vertices do not lead the slots, or a real edge points at a padded
        slot or names a relation outside ``[0, num_relations)``
    """
    node_mask = np.asarray(obs[NODE_MASK]).reshape(n_envs, max_nodes).astype(bool)
    node_counts = node_mask.sum(axis=1)
    # Canonical layout (real vertices first) makes a vertex's slot its rank among real ones.
    if not np.array_equal(node_mask, np.arange(max_nodes) < node_counts[:, None]):
        raise ValueError(f"{owner}: node_mask must put real vertices in the leading slots")
    edge_mask = np.asarray(obs[EDGE_MASK]).reshape(n_envs, -1).astype(bool)
    edge_index = np.asarray(obs[EDGE_INDEX]).reshape(n_envs, 2, -1)
    x = np.asarray(obs[X], dtype=np.float32).reshape(n_envs, max_nodes, node_features)
    edges = {
        "src": edge_index[:, 0][edge_mask],
        "dst": edge_index[:, 1][edge_mask],
        "type": np.asarray(obs[EDGE_TYPE]).reshape(n_envs, -1)[edge_mask],
    }
    if len(edges["src"]):
        limit = np.repeat(node_counts, edge_mask.sum(axis=1))
        bad = (edges["src"] < 0) | (edges["src"] >= limit) | (edges["dst"] < 0) | (edges["dst"] >= limit)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{owner}: a real edge ({int(edges['src'][k])} -> {int(edges['dst'][k])}) points at a padded "
                f"vertex slot or outside the graph ({int(limit[k])} real vertices); edges must join real vertices"
            )
        if edges["type"].min() < 0 or edges["type"].max() >= num_relations:
            raise ValueError(
                f"{owner}: edge_type holds relation ids in [{edges['type'].min()}, {edges['type'].max()}], "
                f"outside [0, num_relations={num_relations})"
            )
    if EDGE_ATTR in obs:
        attr = np.asarray(obs[EDGE_ATTR], dtype=np.float32)
        edges["attr"] = attr.reshape(n_envs, -1, attr.shape[-1])[edge_mask]
    return {"x": x[node_mask]}, node_counts, edges, edge_mask.sum(axis=1), node_mask


class _RingPool:
    """Circular pool of rows shared by the transitions of one ring; see the module docstring.

    Ring row ``pos`` owns one contiguous block of rows (its ``n_envs`` graphs one after the other).

    :param buffer_size: rows of the transition ring
    :param n_envs: transitions per ring row
    :param fields: ``name -> (row shape, dtype)``
    :param initial_capacity: initial number of pool rows
    """

    growth = 1.5  # while filling; amortizes the copies of compaction
    slack = 0.05  # spare rows kept by trim(), for the fluctuation of graph sizes

    def __init__(
        self,
        buffer_size: int,
        n_envs: int,
        fields: dict[str, tuple[tuple[int, ...], Any]],
        initial_capacity: int = 1024,
    ) -> None:
        self.fields = fields
        self.capacity = max(int(initial_capacity), 1)
        self.arrays = {
            name: np.zeros((self.capacity, *shape), dtype=dtype) for name, (shape, dtype) in fields.items()
        }
        # Ring row r's block starts at start[r, 0] and holds count[r].sum() rows.
        self.start = np.zeros((buffer_size, n_envs), dtype=np.int64)
        self.count = np.zeros((buffer_size, n_envs), dtype=np.int32)
        self.used = 0  # rows held by live transitions

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values()) + self.start.nbytes + self.count.nbytes

    @property
    def row_nbytes(self) -> int:
        """Bytes of one pool row over all fields."""
        return sum(a.itemsize * int(np.prod(a.shape[1:])) for a in self.arrays.values())

    def _block(self, row: int) -> tuple[int, int]:
        return int(self.start[row, 0]), int(self.count[row].sum())

    def write(self, pos: int, full: bool, data: dict[str, np.ndarray], counts: np.ndarray) -> None:
        """Store the graphs of ring row ``pos``, whose old data (if ``full``) is dropped.

        :param pos: ring row
        :param full: whether the ring has wrapped (ring row ``pos`` holds the oldest data)
        :param data: ``name -> (sum(counts), *row shape)`` rows of all envs, env after env
        :param counts: ``(n_envs,)`` rows per env
        """
        ring = len(self.start)
        need = int(counts.sum())
        if full:
            self.used -= self._block(pos)[1]
        live_count = ring - 1 if full else pos
        if live_count == 0:
            start = 0 if need <= self.capacity else self._compact(self._live(pos, full), need)
        else:
            newest_start, newest_len = self._block((pos - 1) % ring)
            tail = self._block((pos + 1) % ring if full else 0)[0]
            start = self._place(newest_start + newest_len, tail, need)
            if start < 0:
                start = self._compact(self._live(pos, full), need)
        for name, rows in data.items():
            self.arrays[name][start : start + need] = rows
        self.start[pos] = start + _exclusive_cumsum(counts)
        self.count[pos] = counts
        self.used += need

    def _place(self, head: int, tail: int, need: int) -> int:
        """First free position for ``need`` contiguous rows between the newest block's end
        (``head``) and the oldest live block's start (``tail``), or -1."""
        if self.used == 0:
            return 0 if need <= self.capacity else -1
        if head > tail:  # live rows are [tail, head)
            if self.capacity - head >= need:
                return head
            return 0 if tail >= need else -1
        if head < tail:  # live rows wrap: [tail, capacity) and [0, head)
            return head if tail - head >= need else -1
        return -1 if need else head  # head == tail with live rows: no space left

    def _live(self, pos: int, full: bool) -> np.ndarray:
        """Live ring rows, oldest first, leaving out row ``pos`` (being written)."""
        ring = len(self.start)
        return (np.arange(pos + 1, pos + ring) % ring) if full else np.arange(pos)

    def _compact(self, live: np.ndarray, need: int, capacity: int | None = None) -> int:
        """Copy the live blocks, oldest first, into a new array (larger unless ``capacity`` is
        given); return where the next ``need`` rows go."""
        old_starts = self.start[live, 0]
        indices, new_starts = _segment_indices(old_starts, self.count[live].sum(axis=1))
        if capacity is None:
            capacity = max(math.ceil(self.capacity * self.growth), math.ceil((self.used + need) * 1.25), 16)
        for name, old in self.arrays.items():
            new = np.zeros((capacity, *old.shape[1:]), dtype=old.dtype)
            new[: len(indices)] = old[indices]
            self.arrays[name] = new
        self.start[live] += (new_starts - old_starts)[:, None]
        self.capacity = capacity
        return len(indices)

    def trim(self) -> None:
        """Shrink to the live rows plus a small slack; called once the ring is full, when the
        rows the ring needs are known (if sizes later outgrow it, the pool grows again)."""
        largest_block = int(self.count.sum(axis=1).max())
        capacity = max(math.ceil(self.used * (1 + self.slack)) + 2 * largest_block, 16)
        if capacity < self.capacity:
            self._compact(np.arange(len(self.start)), 0, capacity)

    def shrink(self, row: int, keep: np.ndarray) -> None:
        """Drop the graphs of the envs not in ``keep`` from ring row ``row``, which must hold the
        newest block: the kept graphs move to the block's start, so the freed rows are reused.

        :param row: ring row of the newest block
        :param keep: ``(n_envs,)`` bool, the graphs to keep
        """
        counts = self.count[row].astype(np.int64)
        kept_counts = np.where(keep, counts, 0)
        block_start = int(self.start[row, 0])
        indices, _ = _segment_indices(self.start[row][keep], counts[keep])
        for array in self.arrays.values():
            array[block_start : block_start + len(indices)] = array[indices]  # fancy indexing copies first
        self.used -= int(counts.sum() - kept_counts.sum())
        self.start[row] = block_start + _exclusive_cumsum(kept_counts)
        self.count[row] = kept_counts

    def gather(self, rows: np.ndarray, envs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pool indices of the rows of transitions ``(rows, envs)``, graph after graph.

        :return: flat pool indices, rows per graph, offset of each graph in the flat indices
        """
        counts = self.count[rows, envs].astype(np.int64)
        indices, offsets = _segment_indices(self.start[rows, envs], counts)
        return indices, counts, offsets


class GraphReplayBuffer(ReplayBuffer):
    """Replay buffer for :class:`~sb3_graph.GraphSpace` observations that stores only real vertices
    and edges; memory per transition grows with the graphs actually seen.

    Sampling returns SB3's ``ReplayBufferSamples`` whose observations are
    :class:`~sb3_graph.common.batching.GraphBatch` objects (one disjoint graph built by index arithmetic)
    and whose actions are padded ``(batch_size, max_nodes)`` tensors with 0 in padded slots (the
    actions of padded slots are not stored: the graph critic never reads them). Apart from that,
    samples equal those of SB3's ``DictReplayBuffer`` fed the same transitions under the same numpy
    seed (same FIFO ring, same ``np.random`` calls).

    :param buffer_size: max number of transitions
    :param observation_space: a :class:`~sb3_graph.GraphSpace`
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param device: PyTorch device of the sampled tensors
    :param n_envs: number of parallel environments
    :param optimize_memory_usage: not supported (must be False)
    :param handle_timeout_termination: treat ``TimeLimit.truncated`` ends as non-terminal
    :param initial_capacity: initial vertex/edge rows per pool (pools grow geometrically)
    :param n_steps: n-step returns when > 1, exactly as SB3's ``NStepReplayBuffer``: the reward is
        the discounted sum over up to ``n_steps`` transitions of the same episode, the next
        observation and ``done`` those of the last of them, and ``discounts`` is ``gamma ** k`` for
        the ``k`` transitions summed (the algorithm bootstraps with it). The algorithm aliases set it
        from their ``n_steps`` argument.
    :param gamma: discount factor of the n-step returns
    :param store_expert_actions: keep an expert action per vertex next to each transition (ragged, like
        the observation): :meth:`add` takes ``expert_action=``, samples are
        :class:`ExpertReplayBufferSamples`, :meth:`sample_expert` samples the labelled transitions
        only (:func:`sb3_graph.behaviour_clone` switches it on with :meth:`enable_expert_actions`)
    """

    observation_space: spaces.Dict
    # Defaults for buffers pickled before these options existed.
    edge_features = 0
    n_steps = 1
    gamma = 0.99
    store_expert_actions = False

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        device: torch.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        initial_capacity: int = 4096,
        n_steps: int = 1,
        gamma: float = 0.99,
        store_expert_actions: bool = False,
    ) -> None:
        if int(n_steps) < 1:
            raise ValueError(f"GraphReplayBuffer: n_steps must be >= 1, got {n_steps}")
        if optimize_memory_usage:
            raise ValueError(
                "GraphReplayBuffer: optimize_memory_usage=True is not supported (it already stores only real "
                "vertices and edges); use optimize_memory_usage=False"
            )
        max_nodes, node_features, num_relations = graph_dims(observation_space, action_space)
        edge_features = edge_dims(observation_space)
        # Skip ReplayBuffer.__init__: it would allocate padded arrays.
        super(ReplayBuffer, self).__init__(
            buffer_size, observation_space, action_space, device, n_envs=n_envs
        )
        self.buffer_size = max(buffer_size // n_envs, 1)
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.max_nodes = max_nodes
        self.node_features = node_features
        self.num_relations = num_relations
        self.edge_features = edge_features
        self.initial_capacity = initial_capacity
        self.n_steps = int(n_steps)
        self.gamma = float(gamma)
        self.store_expert_actions = bool(store_expert_actions)
        self.rewards = np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)
        self.dones = np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)
        self.timeouts = np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)
        self._make_pools()

    def _make_pools(self) -> None:
        # Local vertex ids and relation ids in the smallest integer type that holds them.
        index_dtype = np.int16 if self.max_nodes <= np.iinfo(np.int16).max + 1 else np.int32
        type_dtype = np.int8 if self.num_relations <= np.iinfo(np.int8).max + 1 else np.int32
        node_fields = {"x": ((self.node_features,), np.float32)}
        # Endpoints as two 1-D fields: 1-D gathers are faster than gathers of 2-column rows.
        edge_fields = {"src": ((), index_dtype), "dst": ((), index_dtype), "type": ((), type_dtype)}
        if self.edge_features:
            edge_fields["attr"] = ((self.edge_features,), np.float32)
        size, n_envs, cap = self.buffer_size, self.n_envs, self.initial_capacity
        action_fields = {"action": ((), np.float32)}
        if self.store_expert_actions:
            action_fields["expert"] = ((), np.float32)
        self.obs_nodes = _RingPool(size, n_envs, {**node_fields, **action_fields}, cap)
        self.next_obs_nodes = _RingPool(size, n_envs, node_fields, cap)
        self.obs_edges = _RingPool(size, n_envs, edge_fields, cap)
        self.next_obs_edges = _RingPool(size, n_envs, edge_fields, cap)
        # True where a transition's next observation is the observation of the same env's next
        # transition (ring row + 1): it is then stored once, in the observation pools.
        self.next_is_successor = np.zeros((size, n_envs), dtype=bool)
        if self.store_expert_actions:
            self.expert_labelled = np.zeros((size, n_envs), dtype=bool)

    def enable_expert_actions(self) -> None:
        """Start storing expert actions (:class:`GraphReplayBuffer`'s ``store_expert_actions``); the
        transitions already stored carry none."""
        if self.store_expert_actions:
            return
        self.store_expert_actions = True
        pool = self.obs_nodes
        pool.fields = {**pool.fields, "expert": ((), np.float32)}
        pool.arrays["expert"] = np.zeros(pool.capacity, dtype=np.float32)
        self.expert_labelled = np.zeros((self.buffer_size, self.n_envs), dtype=bool)

    @property
    def num_expert_transitions(self) -> int:
        """Stored transitions that carry an expert action."""
        return int(self.expert_labelled.sum()) if self.store_expert_actions else 0

    @property
    def pools(self) -> tuple[_RingPool, ...]:
        return self.obs_nodes, self.next_obs_nodes, self.obs_edges, self.next_obs_edges

    @property
    def nbytes(self) -> int:
        """Bytes held by the buffer's arrays (allocated capacity, not only live rows)."""
        return (
            sum(p.nbytes for p in self.pools) + self.rewards.nbytes + self.dones.nbytes + self.timeouts.nbytes
        ) + (self.expert_labelled.nbytes if self.store_expert_actions else 0)

    def reset(self) -> None:
        super().reset()
        self._make_pools()

    def _split(self, obs: dict[str, np.ndarray]) -> tuple[dict, np.ndarray, dict, np.ndarray, np.ndarray]:
        """Real vertex rows and edge rows of ``n_envs`` padded observations."""
        return split_graphs(
            obs, self.n_envs, self.max_nodes, self.node_features, self.num_relations, "GraphReplayBuffer"
        )

    def add(  # type: ignore[override]
        self,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
        expert_action: np.ndarray | None = None,
    ) -> None:
        """Add one transition per environment.

        :param obs: padded observations, each entry with leading dimension ``n_envs``
        :param next_obs: padded next observations
        :param action: ``(n_envs, max_nodes)`` actions (only real vertices' actions are kept)
        :param reward: ``(n_envs,)``
        :param done: ``(n_envs,)``
        :param infos: one info dict per environment (``TimeLimit.truncated`` is read)
        :param expert_action: ``(n_envs, max_nodes)`` the expert's actions in the units of ``action``
            (only real vertices' are kept), or ``None``: these transitions carry no expert action.
            Only with ``store_expert_actions``.
        """
        nodes, node_counts, edges, edge_counts, node_mask = self._split(obs)
        nodes["action"] = np.asarray(action, dtype=np.float32).reshape(self.n_envs, self.max_nodes)[node_mask]
        if expert_action is not None and not self.store_expert_actions:
            raise ValueError(
                "GraphReplayBuffer.add: expert_action given, but the buffer stores none "
                "(store_expert_actions=True or enable_expert_actions())"
            )
        if self.store_expert_actions:
            labels = np.zeros(node_mask.shape, np.float32) if expert_action is None else expert_action
            nodes["expert"] = np.asarray(labels, dtype=np.float32).reshape(self.n_envs, self.max_nodes)[node_mask]
            self.expert_labelled[self.pos] = expert_action is not None
        next_nodes, next_node_counts, next_edges, next_edge_counts, _ = self._split(next_obs)
        previous = (self.pos - 1) % self.buffer_size
        if (self.pos > 0 or self.full) and previous != self.pos:
            self._link_previous(previous, nodes, node_counts, edges, edge_counts)
        self.obs_nodes.write(self.pos, self.full, nodes, node_counts)
        self.obs_edges.write(self.pos, self.full, edges, edge_counts)
        self.next_obs_nodes.write(self.pos, self.full, next_nodes, next_node_counts)
        self.next_obs_edges.write(self.pos, self.full, next_edges, next_edge_counts)
        self.next_is_successor[self.pos] = False
        self.rewards[self.pos] = np.asarray(reward)
        self.dones[self.pos] = np.asarray(done)
        if self.handle_timeout_termination:
            self.timeouts[self.pos] = np.array([info.get("TimeLimit.truncated", False) for info in infos])
        self.pos += 1
        if self.pos == self.buffer_size:
            if not self.full:
                for pool in self.pools:
                    pool.trim()
            self.full = True
            self.pos = 0

    def _link_previous(
        self, previous: int, nodes: dict, node_counts: np.ndarray, edges: dict, edge_counts: np.ndarray
    ) -> None:
        """Where the newest transition's next observation equals the observation being added (the
        episode goes on), drop its copy from the next-observation pools and point at the successor.
        The dropped graphs are the newest block of those pools, so their rows are reused at once."""
        next_nodes, next_edges = self.next_obs_nodes, self.next_obs_edges
        same = (
            ~self.next_is_successor[previous]
            & (next_nodes.count[previous] == node_counts)
            & (next_edges.count[previous] == edge_counts)
        )
        node_offsets, edge_offsets = _exclusive_cumsum(node_counts), _exclusive_cumsum(edge_counts)
        for env in np.flatnonzero(same):  # n_envs at most, as SB3's loop over infos
            ns, no, nc = next_nodes.start[previous, env], node_offsets[env], node_counts[env]
            es, eo, ec = next_edges.start[previous, env], edge_offsets[env], edge_counts[env]
            same[env] = np.array_equal(
                next_nodes.arrays["x"][ns : ns + nc], nodes["x"][no : no + nc]
            ) and all(
                np.array_equal(next_edges.arrays[name][es : es + ec], edges[name][eo : eo + ec])
                for name in next_edges.fields
            )
        if same.any():
            next_nodes.shrink(previous, ~same)
            next_edges.shrink(previous, ~same)
            self.next_is_successor[previous] = same

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:  # type: ignore[override]
        """Sample ``batch_size`` transitions uniformly (with replacement), as SB3 does.

        :param batch_size: number of transitions
        :param env: VecNormalize wrapper, for reward normalization only
        :return: samples with :class:`GraphBatch` observations and padded actions
        """
        upper_bound = self.buffer_size if self.full else self.pos
        if upper_bound == 0:
            raise ValueError("GraphReplayBuffer.sample: the buffer is empty")
        # The global numpy generator, as in SB3, so that the algorithm's seed applies.
        batch_inds = np.random.randint(0, upper_bound, size=batch_size)  # noqa: NPY002
        return self._get_samples(batch_inds, env=env)

    def sample_expert(self, batch_size: int, env: VecNormalize | None = None) -> ExpertReplayBufferSamples:
        """Sample ``batch_size`` of the transitions that carry an expert action, uniformly (with
        replacement, the global numpy generator).

        :param batch_size: number of transitions
        :param env: VecNormalize wrapper, for reward normalization only
        :raises ValueError: no stored transition carries an expert action
        """
        labelled = np.flatnonzero(self.expert_labelled) if self.store_expert_actions else np.zeros(0, np.int64)
        if not len(labelled):
            raise ValueError("GraphReplayBuffer.sample_expert: no stored transition carries an expert action")
        chosen = labelled[np.random.randint(0, len(labelled), size=batch_size)]  # noqa: NPY002
        rows, envs = np.divmod(chosen, self.n_envs)
        return self._get_samples(rows, env=env, env_indices=envs)  # type: ignore[return-value]

    @staticmethod
    def _take(
        pools: tuple[_RingPool, _RingPool], name: str, indices: np.ndarray, split: tuple | None
    ) -> np.ndarray:
        """Rows ``indices`` of field ``name``; with ``split = (own, other)`` positions, the rows at
        positions ``other`` are read from ``pools[1]``."""
        own = pools[0].arrays[name]
        if split is None:
            return np.take(own, indices, axis=0)
        own_positions, other_positions = split
        out = np.empty((len(indices), *own.shape[1:]), dtype=own.dtype)
        out[own_positions] = np.take(own, indices[own_positions], axis=0)
        out[other_positions] = np.take(pools[1].arrays[name], indices[other_positions], axis=0)
        return out

    def _graph_batch(
        self,
        nodes: tuple[_RingPool, _RingPool],
        edges: tuple[_RingPool, _RingPool],
        rows: np.ndarray,
        envs: np.ndarray,
        successor: np.ndarray | None = None,
    ) -> tuple[GraphBatch, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """One disjoint graph of the transitions ``(rows, envs)`` from the first pools, or for the
        graphs where ``successor`` is True from the second pools at ring row ``rows + 1``."""
        starts = [pools[0].start[rows, envs] for pools in (nodes, edges)]
        counts = [pools[0].count[rows, envs].astype(np.int64) for pools in (nodes, edges)]
        if successor is not None:
            following = (rows + 1) % self.buffer_size
            for k, pools in enumerate((nodes, edges)):
                starts[k] = np.where(successor, pools[1].start[following, envs], starts[k])
                counts[k] = np.where(successor, pools[1].count[following, envs], counts[k])
        node_idx, node_offsets = _segment_indices(starts[0], counts[0])
        edge_idx, _ = _segment_indices(starts[1], counts[1])
        node_alt = edge_alt = None
        if successor is not None:
            node_rows, edge_rows = np.repeat(successor, counts[0]), np.repeat(successor, counts[1])
            node_alt = (np.flatnonzero(~node_rows), np.flatnonzero(node_rows))
            edge_alt = (np.flatnonzero(~edge_rows), np.flatnonzero(edge_rows))
        num_graphs = len(rows)
        batch = np.repeat(np.arange(num_graphs), counts[0])
        node_slot = np.arange(len(node_idx)) - node_offsets[batch]
        # Local endpoints + the first vertex id of the edge's graph = ids in the disjoint graph.
        local = np.stack([self._take(edges, name, edge_idx, edge_alt) for name in ("src", "dst")]).astype(
            np.int64
        )
        edge_index = local + np.repeat(node_offsets, counts[1])
        device = self.device
        edge_attr = None
        if self.edge_features:
            edge_attr = torch.as_tensor(self._take(edges, "attr", edge_idx, edge_alt), device=device)
        graphs = GraphBatch(
            x=torch.as_tensor(self._take(nodes, "x", node_idx, node_alt), device=device),
            edge_index=torch.as_tensor(edge_index, device=device),
            edge_type=torch.as_tensor(
                self._take(edges, "type", edge_idx, edge_alt).astype(np.int64), device=device
            ),
            batch=torch.as_tensor(batch, device=device),
            node_slot=torch.as_tensor(node_slot, device=device),
            num_graphs=num_graphs,
            max_nodes=self.max_nodes,
            edge_attr=edge_attr,
        )
        return graphs, (node_idx, batch, node_slot)

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None, env_indices: np.ndarray | None = None
    ) -> ReplayBufferSamples | ExpertReplayBufferSamples:
        check_vec_normalize(env, self.observation_space)
        if env_indices is None:
            env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))  # noqa: NPY002
        observations, (node_idx, batch, node_slot) = self._graph_batch(
            (self.obs_nodes, self.obs_nodes), (self.obs_edges, self.obs_edges), batch_inds, env_indices
        )
        if self.n_steps > 1:
            last, rewards, discounts = self._n_step_returns(batch_inds, env_indices, env)
        else:
            last, discounts = batch_inds, None
            rewards = self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env)
        next_observations, _ = self._graph_batch(
            (self.next_obs_nodes, self.obs_nodes),
            (self.next_obs_edges, self.obs_edges),
            last,
            env_indices,
            successor=self.next_is_successor[last, env_indices],
        )
        actions = np.zeros((len(batch_inds), self.max_nodes), dtype=np.float32)
        actions[batch, node_slot] = self.obs_nodes.arrays["action"][node_idx]
        dones = self.dones[last, env_indices] * (1 - self.timeouts[last, env_indices])
        samples = ReplayBufferSamples(
            observations=observations,  # type: ignore[arg-type]
            actions=self.to_torch(actions),
            next_observations=next_observations,  # type: ignore[arg-type]
            dones=self.to_torch(dones.reshape(-1, 1)),
            rewards=self.to_torch(rewards),
            discounts=None if discounts is None else self.to_torch(discounts),
        )
        if not self.store_expert_actions:
            return samples
        expert = np.zeros((len(batch_inds), self.max_nodes), dtype=np.float32)
        expert[batch, node_slot] = self.obs_nodes.arrays["expert"][node_idx]
        labelled = self.expert_labelled[batch_inds, env_indices]
        return ExpertReplayBufferSamples(
            *samples, expert_actions=self.to_torch(expert), expert_mask=torch.as_tensor(labelled, device=self.device)
        )

    def _n_step_returns(
        self, batch_inds: np.ndarray, env_indices: np.ndarray, env: VecNormalize | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """SB3's ``NStepReplayBuffer`` arithmetic: the ring row of the last transition summed,
        ``(B, 1)`` n-step returns and ``(B, 1)`` bootstrap discounts."""
        # The newest transition counts as truncated (unless done), so that no window runs past it
        # into overwritten or empty rows.
        newest = self.pos - 1
        original = self.timeouts[newest].copy()
        self.timeouts[newest] = np.logical_or(original, np.logical_not(self.dones[newest]))
        try:
            steps = np.arange(self.n_steps)
            rows = (batch_inds[:, None] + steps) % self.buffer_size
            columns = env_indices[:, None]
            rewards = self._normalize_reward(self.rewards[rows, columns], env)
            ends = np.logical_or(self.dones[rows, columns], self.timeouts[rows, columns])
            end = np.where(ends.any(axis=1), ends.argmax(axis=1), self.n_steps - 1)
            mask = steps[None] <= end[:, None]
            returns = (rewards * self.gamma ** steps.astype(np.float32) * mask).sum(axis=1, keepdims=True)
            discounts = (self.gamma ** mask.sum(axis=1, keepdims=True)).astype(np.float32)
            # The caller reads done * (1 - timeout) of `last` after the change is undone: the same
            # value (the changed flag only ever marks a transition that is not done).
            last = (batch_inds + end) % self.buffer_size
        finally:
            self.timeouts[newest] = original
        return last, returns.astype(np.float32), discounts


def gather_graph_batch(
    nodes: dict[str, np.ndarray],
    edges: dict[str, np.ndarray],
    node_starts: np.ndarray,
    node_counts: np.ndarray,
    edge_starts: np.ndarray,
    edge_counts: np.ndarray,
    max_nodes: int,
    device: torch.device | str,
) -> tuple[GraphBatch, np.ndarray, np.ndarray, np.ndarray]:
    """One disjoint graph of graphs stored as row segments of flat pools (no loop over graphs).

    :param nodes: vertex pool, ``{"x": (rows, F), ...}``
    :param edges: edge pool, ``{"src", "dst", "type"[, "attr"]}`` with local vertex ids
    :param node_starts: ``(B,)`` first vertex row of each graph
    :param node_counts: ``(B,)`` vertex rows of each graph
    :param edge_starts: ``(B,)`` first edge row of each graph
    :param edge_counts: ``(B,)`` edge rows of each graph
    :param max_nodes: vertex slots of the padded layout
    :param device: device of the tensors
    :return: the batch, and the vertex rows read, each vertex's graph and its slot (numpy)
    """
    node_counts = node_counts.astype(np.int64, copy=False)
    edge_counts = edge_counts.astype(np.int64, copy=False)
    node_idx, node_offsets = _segment_indices(node_starts, node_counts)
    edge_idx, _ = _segment_indices(edge_starts, edge_counts)
    batch = np.repeat(np.arange(len(node_starts)), node_counts)
    node_slot = np.arange(len(node_idx)) - node_offsets[batch]
    first_vertex = np.repeat(node_offsets, edge_counts)
    edge_index = np.stack([edges["src"][edge_idx], edges["dst"][edge_idx]]).astype(np.int64) + first_vertex
    graphs = GraphBatch(
        x=torch.as_tensor(nodes["x"][node_idx], device=device),
        edge_index=torch.as_tensor(edge_index, device=device),
        edge_type=torch.as_tensor(edges["type"][edge_idx].astype(np.int64), device=device),
        batch=torch.as_tensor(batch, device=device),
        node_slot=torch.as_tensor(node_slot, device=device),
        num_graphs=len(node_starts),
        max_nodes=max_nodes,
        edge_attr=torch.as_tensor(edges["attr"][edge_idx], device=device) if "attr" in edges else None,
    )
    return graphs, node_idx, batch, node_slot


class GraphRolloutBuffer(RolloutBuffer):
    """A rollout buffer (PPO, A2C) for :class:`~sb3_graph.GraphSpace` observations that stores only
    real vertices and edges.

    Each step's graphs are split into their real vertex rows (with each vertex's action) and edge
    rows; :meth:`get` joins them once per rollout into flat pools and yields minibatches of
    ``batch_size`` *graphs* (transitions), each as one disjoint :class:`~sb3_graph.common.batching.GraphBatch`
    built by index arithmetic, with padded ``(batch_size, max_nodes)`` actions (0 in padded
    slots). Returns, advantages (GAE) and the minibatch order are SB3's: under the same numpy seed
    the minibatches hold the same transitions as SB3's ``DictRolloutBuffer`` (advantage
    normalization, per minibatch, is the algorithm's, as in SB3).

    :param buffer_size: steps per environment in one rollout (``n_steps``)
    :param observation_space: a :class:`~sb3_graph.GraphSpace`
    :param action_space: ``Box`` of shape ``(max_nodes,)``
    :param device: PyTorch device of the sampled tensors
    :param gae_lambda: GAE's lambda
    :param gamma: discount factor
    :param n_envs: number of parallel environments
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        device: torch.device | str = "auto",
        gae_lambda: float = 1,
        gamma: float = 0.99,
        n_envs: int = 1,
    ) -> None:
        self.max_nodes, self.node_features, self.num_relations = graph_dims(observation_space, action_space)
        self.edge_features = edge_dims(observation_space)
        super().__init__(buffer_size, observation_space, action_space, device, gae_lambda, gamma, n_envs)

    def reset(self) -> None:
        shape = (self.buffer_size, self.n_envs)
        self.rewards = np.zeros(shape, dtype=np.float32)
        self.returns = np.zeros(shape, dtype=np.float32)
        self.episode_starts = np.zeros(shape, dtype=np.float32)
        self.values = np.zeros(shape, dtype=np.float32)
        self.log_probs = np.zeros(shape, dtype=np.float32)
        self.advantages = np.zeros(shape, dtype=np.float32)
        self.node_counts = np.zeros(shape, dtype=np.int64)
        self.edge_counts = np.zeros(shape, dtype=np.int64)
        self._step_nodes: list[dict[str, np.ndarray]] = []
        self._step_edges: list[dict[str, np.ndarray]] = []
        self._expert: np.ndarray | None = None  # (buffer_size, n_envs, max_nodes) once a step is labelled
        self.generator_ready = False
        BaseBuffer.reset(self)

    def label_step(self, step: int, expert_action: np.ndarray) -> None:
        """Label the observations of rollout step ``step`` (of every environment) with an expert's
        actions (a regularizer toward the expert: ``bc_coef`` of PPO and A2C). The minibatches of a
        rollout with labels are :class:`ExpertRolloutBufferSamples` (unlabelled steps masked out).

        :param step: the step's index in the rollout (it may be labelled before it is added)
        :param expert_action: ``(n_envs, max_nodes)`` expert actions in the action space's units
        """
        if self._expert is None:
            self._expert = np.zeros((self.buffer_size, self.n_envs, self.max_nodes), dtype=np.float32)
            self._expert_steps = np.zeros(self.buffer_size, dtype=bool)
        self._expert[step] = np.asarray(expert_action, dtype=np.float32).reshape(self.n_envs, self.max_nodes)
        self._expert_steps[step] = True

    @property
    def nbytes(self) -> int:
        """Bytes of the stored graphs and per-step arrays (after a rollout)."""
        rows = sum(a.nbytes for step in (*self._step_nodes, *self._step_edges) for a in step.values())
        arrays = (self.rewards, self.returns, self.episode_starts, self.values, self.log_probs, self.advantages)
        return rows + sum(a.nbytes for a in arrays) + self.node_counts.nbytes + self.edge_counts.nbytes

    def add(  # type: ignore[override]
        self,
        obs: dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        episode_start: np.ndarray,
        value: torch.Tensor,
        log_prob: torch.Tensor,
    ) -> None:
        """Add one step of every environment.

        :param obs: padded observations, each entry with leading dimension ``n_envs``
        :param action: ``(n_envs, max_nodes)`` actions (only real vertices' actions are kept)
        :param reward: ``(n_envs,)``
        :param episode_start: ``(n_envs,)`` start-of-episode flags
        :param value: ``(n_envs, 1)`` value estimates
        :param log_prob: ``(n_envs,)`` log-probabilities of the actions
        """
        if self.pos >= self.buffer_size:
            raise ValueError("GraphRolloutBuffer.add: the rollout is full; call reset() first")
        nodes, node_counts, edges, edge_counts, node_mask = split_graphs(
            obs, self.n_envs, self.max_nodes, self.node_features, self.num_relations, "GraphRolloutBuffer"
        )
        nodes["action"] = np.asarray(action, dtype=np.float32).reshape(self.n_envs, self.max_nodes)[node_mask]
        self._step_nodes.append(nodes)
        self._step_edges.append(edges)
        self.node_counts[self.pos] = node_counts
        self.edge_counts[self.pos] = edge_counts
        self.rewards[self.pos] = np.asarray(reward)
        self.episode_starts[self.pos] = np.asarray(episode_start)
        self.values[self.pos] = value.clone().cpu().numpy().flatten()
        self.log_probs[self.pos] = log_prob.clone().cpu().numpy().reshape(-1)
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True

    def _prepare(self) -> None:
        """Join the steps into flat pools and flatten every per-transition array env-major
        (SB3's ``swap_and_flatten`` order: transition ``k`` is env ``k // n_steps``, step ``k % n_steps``)."""
        self._nodes = {k: np.concatenate([s[k] for s in self._step_nodes]) for k in self._step_nodes[0]}
        self._edges = {k: np.concatenate([s[k] for s in self._step_edges]) for k in self._step_edges[0]}
        if self._expert is not None:
            # Rows step after step, env after env, as the vertex pool.
            real = np.arange(self.max_nodes) < self.node_counts.reshape(-1, 1)
            self._nodes["expert"] = self._expert.reshape(-1, self.max_nodes)[real]
            steps = np.repeat(self._expert_steps[:, None], self.n_envs, axis=1)
            self._expert_labelled = steps.swapaxes(0, 1).reshape(-1)  # env-major, as swap_and_flatten
        flat = {}
        for name, counts in (("node", self.node_counts), ("edge", self.edge_counts)):
            starts = _exclusive_cumsum(counts.reshape(-1)).reshape(counts.shape)  # rows step after step
            flat[f"{name}_starts"] = starts.swapaxes(0, 1).reshape(-1)
            flat[f"{name}_counts"] = counts.swapaxes(0, 1).reshape(-1)
        self._flat = flat
        for name in ("values", "log_probs", "advantages", "returns"):
            self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
        self.generator_ready = True

    def get(self, batch_size: int | None = None):  # type: ignore[override]
        """Yield minibatches of ``batch_size`` graphs in a random order (all at once for ``None``).

        :param batch_size: graphs per minibatch
        :return: a generator of ``RolloutBufferSamples`` with :class:`GraphBatch` observations
        """
        assert self.full, "GraphRolloutBuffer.get: the rollout is not complete"
        indices = np.random.permutation(self.buffer_size * self.n_envs)  # noqa: NPY002 (SB3's generator)
        if not self.generator_ready:
            self._prepare()
        if batch_size is None:
            batch_size = self.buffer_size * self.n_envs
        for start in range(0, self.buffer_size * self.n_envs, batch_size):
            yield self._get_samples(indices[start : start + batch_size])

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> RolloutBufferSamples:
        flat = self._flat
        graphs, node_idx, batch, node_slot = gather_graph_batch(
            self._nodes,
            self._edges,
            flat["node_starts"][batch_inds],
            flat["node_counts"][batch_inds],
            flat["edge_starts"][batch_inds],
            flat["edge_counts"][batch_inds],
            self.max_nodes,
            self.device,
        )
        actions = np.zeros((len(batch_inds), self.max_nodes), dtype=np.float32)
        actions[batch, node_slot] = self._nodes["action"][node_idx]
        samples = RolloutBufferSamples(
            observations=graphs,  # type: ignore[arg-type]
            actions=self.to_torch(actions),
            old_values=self.to_torch(self.values[batch_inds].flatten()),
            old_log_prob=self.to_torch(self.log_probs[batch_inds].flatten()),
            advantages=self.to_torch(self.advantages[batch_inds].flatten()),
            returns=self.to_torch(self.returns[batch_inds].flatten()),
        )
        if "expert" not in self._nodes:
            return samples
        expert = np.zeros((len(batch_inds), self.max_nodes), dtype=np.float32)
        expert[batch, node_slot] = self._nodes["expert"][node_idx]
        labelled = torch.as_tensor(self._expert_labelled[batch_inds], device=self.device)
        return ExpertRolloutBufferSamples(*samples, expert_actions=self.to_torch(expert), expert_mask=labelled)  # type: ignore[return-value]
