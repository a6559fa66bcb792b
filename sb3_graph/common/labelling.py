"""An expert's labels in parallel and resumable: each sub-environment's share of a cloning round as one job.

Labelling is the costly part of cloning a search (``lookahead`` asks tens of milliseconds of rollouts per
state, the network's update a fraction of that) and it is embarrassingly parallel. :class:`ShardedCollector`
is a ``collector`` of :func:`~sb3_graph.behaviour_clone`: it runs each sub-environment's steps of a round as
one job on an executor (:mod:`sb3_graph.common.executors`: local processes, a Dask cluster or Ray, the
executors of a domain's evaluation) and stacks the shards into the round's
:class:`~sb3_graph.Demonstrations`, as if one VecEnv had collected them in lockstep.

- **Seeds.** Sub-environment ``i`` of round ``k`` is ``make_vec_env(env_id, 1, seed + k * n_envs + i)``, a new
  episode each round (in a VecEnv stepped across rounds the episodes go on). Round 0 is then the lockstep
  collection of the model's own VecEnv (``make_vec_env(env_id, n_envs, seed)``) bit for bit, since its expert
  acts alone there (``beta(0) = 1``); ``tests/test_labelling.py`` checks it.
- **DAgger.** In a round with ``beta < 1`` the learner acts too: its policy travels with the round's jobs
  (pickled once per worker) and each shard draws its own choices from a seed of the model's random stream.
- **Resuming.** With a ``folder``, each shard is written there as it comes in (``round-<k>-env-<i>.npz``,
  atomically, never over an existing file) and read back instead of labelling again: a run cut short (a
  session's end, a lost cluster) labels only the shards it lacks, the learner re-fitted on the rounds before.

The workers import the environment's package (``packages``) and build the expert from its factory by name
(:func:`sb3_graph.plugins.expert_factory`): nothing but names, settings and the policy is sent.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sb3_graph.common.cloning import Demonstrations, expert_step
from sb3_graph.common.executors import EXECUTORS, JobExecutor, make_executor
from sb3_graph.files.output_folders import write_atomically


@dataclass(frozen=True)
class LabellingJob:
    """What every shard of a round needs (sent to each worker once).

    :param env_id: the gymnasium id
    :param env_kwargs: its ``gym.make`` keyword arguments
    :param expert: the expert's spec, as ``pretrain_from``
    :param factory: import path of the expert factory, ``factory(expert, vec_env) -> expert``
    :param packages: modules to import first (they register ``env_id``)
    :param policy: the learner's policy, in a round where it acts (``None``: the expert alone)
    """

    env_id: str
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    expert: str = ""
    factory: str = ""
    packages: tuple[str, ...] = ()
    policy: Any = None


def label_shard(item: tuple[int, int, float, int], job: LabellingJob) -> dict[str, np.ndarray]:
    """One sub-environment's steps of a round, with the expert's labels (a job of :class:`ShardedCollector`).

    :param item: ``(seed, steps, beta, choice_seed)``: the sub-environment's seed, its VecEnv steps, the
        probability that the expert acts, and the seed of the expert-or-learner draws
    :return: the shard's :meth:`Demonstrations.arrays` (one environment)
    """
    import torch
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_graph.registry import import_object

    torch.set_num_threads(1)
    for name in job.packages:
        importlib.import_module(name)
    seed, steps, beta, choice_seed = item
    env = make_vec_env(job.env_id, n_envs=1, seed=seed, env_kwargs=job.env_kwargs)
    try:
        expert = import_object(job.factory)(job.expert, env)
        rng = np.random.default_rng(choice_seed)
        recorder, obs = Demonstrations(), env.reset()
        for _ in range(steps):
            new_obs, stored, labels, rewards, dones, infos, by_expert = expert_step(env, job.policy, expert, obs,
                                                                                    beta, rng)  # fmt: skip
            recorder.append(obs, new_obs, stored, labels, rewards, dones, infos, by_expert)
            obs = new_obs
        return recorder.arrays()
    finally:
        env.close()


class ShardedCollector:
    """``collector(round, beta, steps)`` for :func:`~sb3_graph.behaviour_clone`: each sub-environment's share of
    the round labelled as one job on an executor, the round cached in ``folder`` (see the module docstring).

    :param model: the learner (its policy acts in rounds with ``beta < 1``; its VecEnv gives ``n_envs``)
    :param job: the environment, the expert and the packages (its ``policy`` is set per round)
    :param seed: the seed of the model's VecEnv (sub-environment ``i`` of round ``k``: ``seed + k * n_envs + i``)
    :param executor: ``"local"``, ``"dask"``, ``"ray"``, or a :class:`~sb3_graph.common.executors.JobExecutor`
    :param workers: parallel workers (an executor at ``address`` brings its own)
    :param address: an existing cluster's address
    :param folder: where each shard is kept and found again (``None``: nothing kept)
    """

    def __init__(
        self,
        model: Any,
        job: LabellingJob,
        seed: int,
        executor: str | JobExecutor = "local",
        workers: int = 1,
        address: str | None = None,
        folder: str | Path | None = None,
    ) -> None:
        if isinstance(executor, str) and executor not in EXECUTORS:
            raise ValueError(f"labelling executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"labelling workers must be an integer >= 1, got {workers!r}")
        self.model, self.job, self.seed = model, job, int(seed)
        self.executor, self.workers, self.address = executor, int(workers), address
        self.folder = None if folder is None else Path(folder)
        self.labelled: list[int] = []  # rounds labelled here (the others were read from the folder)

    def path(self, round_index: int, env_index: int) -> Path | None:
        """The file of sub-environment ``env_index``'s shard of round ``round_index`` (``None`` without a folder)."""
        return None if self.folder is None else self.folder / f"round-{round_index}-env-{env_index}.npz"

    def cached(self, round_index: int, env_index: int, steps: int) -> Demonstrations | None:
        """The shard kept in the folder, if it is there, readable and of ``steps`` steps."""
        path = self.path(round_index, env_index)
        if path is None or not path.is_file():
            return None
        try:
            shard = Demonstrations.load(path)
        except ValueError:
            return None  # unreadable (cut short?): labelled again, the file stays
        return shard if shard.actions.shape[:2] == (steps, 1) else None

    def __call__(self, round_index: int, beta: float, steps: int) -> Demonstrations:
        n_envs = self.model.get_env().num_envs
        # drawn before the cache is read, so that a resumed run's later rounds draw what the first run's did
        choice_seeds = np.random.randint(2**31, size=n_envs)  # noqa: NPY002 (follows the model's seed)
        shards = [self.cached(round_index, i, steps) for i in range(n_envs)]
        missing = [i for i, shard in enumerate(shards) if shard is None]
        if missing:
            job = self.job if beta >= 1.0 else _with_policy(self.job, self.model.policy)
            items = [(self.seed + round_index * n_envs + i, steps, float(beta), int(choice_seeds[i])) for i in missing]
            own = not isinstance(self.executor, JobExecutor)
            executor = make_executor(self.executor, self.workers, self.address) if own else self.executor
            try:
                for k, arrays in executor.map_unordered(label_shard, items, job):
                    shard = shards[missing[k]] = Demonstrations.from_arrays(arrays)
                    path = self.path(round_index, missing[k])
                    if path is not None:  # as it comes, atomically, never over a file that is there
                        write_atomically(path, shard.save)
            finally:
                if own:
                    executor.close()
            self.labelled.append(round_index)
        return Demonstrations.stack(shards)  # type: ignore[arg-type]


def _with_policy(job: LabellingJob, policy: Any) -> LabellingJob:
    import copy

    import torch

    own = copy.deepcopy(policy).to(torch.device("cpu"))
    own.set_training_mode(False)
    return LabellingJob(job.env_id, job.env_kwargs, job.expert, job.factory, job.packages, own)
