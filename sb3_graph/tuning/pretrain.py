"""Behaviour cloning in a tuning study: clone once, reuse in every trial.

An entry with ``pretrain_from`` clones its expert into each trial's model before ``learn`` (as
``sb3-graph train --pretrain-from``). Collecting the demonstrations is the costly part (the expert and
the environments: about 17 ms per transition on the intersection), so a study does it once and keeps
two kinds of files in its cache folder (``--pretrain-cache``, by default ``<study>.pretrain/`` next to a
SQLite or journal storage file):

- ``demonstrations-<hash>.npz``: the collected transitions (:class:`~sb3_graph.Demonstrations`),
  under a hash of the expert spec, the env id, the trial's env kwargs (its whole env config: reward
  weights and config keys included, since the stored rewards and the dynamics depend on them),
  ``n_envs``, ``pretrain_transitions`` and the DAgger settings; with DAgger rounds (``pretrain_rounds`` > 1)
  also everything the clone's key holds, since the learner that acts in the later rounds chooses the states;
- ``clone-<hash>.pt``: the model's parameters after cloning and the critics' warm-up (policy,
  optimizers, entropy coefficient), under the demonstrations' hash plus the algorithm, every entry key
  that shapes the model or its updates (``policy_kwargs``, ``learning_rate``, ``batch_size``, ``gamma``,
  ``pretrain_steps``...) and the SHA-256 of ``--init-weights``.

A trial whose keys match reuses the file instead of collecting (or cloning) again; a trial whose keys
differ (a sampled reward weight, config key or algorithm setting) makes its own. The files come from the
first trial that needed them (its seed). They are written atomically (a temporary file, then a hard link
that never replaces an existing file) and read without unpickling (``np.load(allow_pickle=False)``,
``torch.load(weights_only=True)``).
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import torch as th

from sb3_graph.common.cloning import Demonstrations, behaviour_clone
from sb3_graph.common.experts import PRETRAIN_STEPS, PRETRAIN_TRANSITIONS, make_expert
from sb3_graph.common.labelling import LabellingJob, ShardedCollector
from sb3_graph.files.output_folders import write_atomically
from sb3_graph.plugins import expert_factory, gym_packages

#: Entry keys that do not change the cloned model (RL's budget, callbacks, the RL-time regularizer).
NOT_CLONING_KEYS = ("n_timesteps", "callback", "bc_coef", "env_kwargs")


def default_cache_folder(storage_url: str, study_name: str) -> Path:
    """``<folder of the storage file>/<study>.pretrain`` (``studies/<study>.pretrain`` for a server storage).

    :param storage_url: the study's storage URL (``sqlite:///PATH``, ``journal://PATH``, ``postgresql://...``)
    :param study_name: the study's name
    """
    for prefix in ("sqlite:///", "journal://"):
        if storage_url.startswith(prefix):
            return Path(storage_url[len(prefix):]).parent / f"{study_name}.pretrain"
    return Path("studies") / f"{study_name}.pretrain"


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def demonstrations_key(
    entry: dict[str, Any], env_id: str, algo: str = "", init_weights_sha256: str = ""
) -> dict[str, Any]:
    """What the collected demonstrations depend on; with DAgger (``pretrain_rounds`` > 1) also the learner
    that acts in the later rounds (the algorithm, its settings and its start), since it chooses the states."""
    key = {
        "expert": str(entry["pretrain_from"]),
        "env": env_id,
        "env_kwargs": entry.get("env_kwargs") or {},
        "n_envs": int(entry.get("n_envs", 1)),
        "transitions": int(entry.get("pretrain_transitions", PRETRAIN_TRANSITIONS)),
    }
    for name in ("pretrain_rounds", "pretrain_beta"):  # DAgger: who acted shapes what was labelled
        if name in entry:
            key[name] = entry[name]
    if int(entry.get("pretrain_rounds", 1)) > 1:
        settings = {name: value for name, value in entry.items() if name not in NOT_CLONING_KEYS}
        key["learner"] = {"algo": algo, "entry": settings, "init": init_weights_sha256}
    return key


def dagger_arguments(entry: dict[str, Any]) -> dict[str, Any]:
    """``behaviour_clone``'s ``rounds`` and ``beta`` of an entry: ``pretrain_rounds`` rounds (default 1), round ``k``
    acting with the expert with probability ``pretrain_beta ** k`` (default 1: the expert always acts)."""
    rounds, beta = int(entry.get("pretrain_rounds", 1)), float(entry.get("pretrain_beta", 1.0))
    return {"rounds": rounds, "beta": lambda k: beta**k}


def clone_key(entry: dict[str, Any], env_id: str, algo: str, init_weights_sha256: str) -> dict[str, Any]:
    """What the cloned parameters depend on: the demonstrations, the algorithm and its settings, the start."""
    settings = {key: value for key, value in entry.items() if key not in NOT_CLONING_KEYS}
    key = demonstrations_key(entry, env_id, algo, init_weights_sha256)
    return {**key, "algo": algo, "entry": settings, "init": init_weights_sha256}


def _torch_state(model: Any) -> dict[str, Any]:
    """The model's parameters, optimizer states and torch variables (SAC's ``log_ent_coef``)."""
    _, variables = model._get_torch_save_params()
    state = {"parameters": model.get_parameters(), "variables": {}, "n_updates": int(getattr(model, "_n_updates", 0))}
    for name in variables:
        value = _attribute(model, name)
        if isinstance(value, th.Tensor):
            state["variables"][name] = value.detach().cpu()
    return state


def _attribute(model: Any, dotted: str) -> Any:
    value = model
    for part in dotted.split("."):
        value = getattr(value, part, None)
    return value


def _expert_settings(expert: Any) -> dict[str, Any]:
    """What the expert's labels depend on beyond its spec (its ``cache_key``: a search's parameters, whose defaults
    may change between versions), for the keys; nothing for an expert without one (their keys stay as they were)."""
    settings = getattr(expert, "cache_key", None)
    return {} if settings is None else {"expert_settings": settings}


def _read_clone(path: Path) -> dict[str, Any] | None:
    """The cloned parameters kept at ``path``, or ``None`` (no such file, or unreadable: clone again)."""
    if not path.is_file():
        return None
    try:
        return th.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 (any unreadable file: clone again)
        return None


def _load_torch_state(model: Any, state: dict[str, Any]) -> None:
    model.set_parameters(state["parameters"], exact_match=True, device=model.device)
    with th.no_grad():
        for name, value in state["variables"].items():
            _attribute(model, name).copy_(value.to(model.device))
    model._n_updates = int(state["n_updates"])


def pretrain_trial(
    model: Any,
    entry: dict[str, Any],
    env_id: str,
    train_env: Any,
    algo: str,
    folder: Path | None,
    init_weights: Path | None = None,
    labelling: dict[str, Any] | None = None,
) -> dict[str, Any] | None:
    """Clone the entry's ``pretrain_from`` expert into a trial's model, through the study's cache.

    :param model: the trial's fresh model (after ``--init-weights``)
    :param entry: the trial's entry (its sampled parameters in place)
    :param env_id: the study's env id
    :param train_env: the model's VecEnv
    :param algo: the ``--algo`` name
    :param folder: the study's cache folder (``None``: clone without a cache)
    :param init_weights: the ``--init-weights`` file, if any (its hash enters the clone's key)
    :param labelling: label on an executor, resumably (:class:`~sb3_graph.common.labelling.ShardedCollector`):
        ``seed`` (the model's VecEnv's), ``executor``, ``workers`` and ``address``; each shard is kept in the
        folder ``demonstrations-<hash>/`` (a new episode per round and sub-environment, so another hash than
        the lockstep collection's ``demonstrations-<hash>.npz``)
    :return: ``None`` without ``pretrain_from``; else ``cache`` (``"none"``, ``"demonstrations"`` or
        ``"clone"``: what was reused), ``transitions``, ``seconds`` and the two files' names
    """
    if entry.get("pretrain_from") is None:
        return None
    if folder is None:  # a cache of one trial
        with tempfile.TemporaryDirectory(prefix="pretrain-") as temporary:
            return pretrain_trial(model, entry, env_id, train_env, algo, Path(temporary), init_weights, labelling)
    if labelling is not None:
        return _pretrain_sharded(model, entry, env_id, train_env, algo, Path(folder), init_weights, labelling)
    folder = Path(folder)
    tic = time.perf_counter()
    init_hash = hashlib.sha256(init_weights.read_bytes()).hexdigest() if init_weights is not None else ""
    expert = make_expert(str(entry["pretrain_from"]), env_id, train_env)  # on-policy bc_coef labels with it
    settings = _expert_settings(expert)
    key = {**demonstrations_key(entry, env_id, algo, init_hash), **settings}
    demo_path = folder / f"demonstrations-{_digest(key)[:32]}.npz"
    clone_path = folder / f"clone-{_digest({**clone_key(entry, env_id, algo, init_hash), **settings})[:32]}.pt"
    demonstrations = None
    if demo_path.is_file():
        try:
            demonstrations = Demonstrations.load(demo_path)
        except ValueError:
            demonstrations = None  # unreadable (cut short?): collect again, the file stays
    state = _read_clone(clone_path) if demonstrations is not None else None
    steps = int(entry.get("pretrain_steps", PRETRAIN_STEPS))
    critic_steps = entry.get("pretrain_critic_steps")
    result = behaviour_clone(
        model,
        expert,
        transitions=int(entry.get("pretrain_transitions", demonstrations_key(entry, env_id)["transitions"])),
        gradient_steps=0 if state is not None else steps,
        batch_size=int(getattr(model, "batch_size", 256) or 256),
        critic_steps=0 if state is not None else (None if critic_steps is None else int(critic_steps)),
        demonstrations=demonstrations,
        record=demonstrations is None,
        **({} if demonstrations is not None else dagger_arguments(entry)),
    )
    if state is not None:
        _load_torch_state(model, state)
        cache = "clone"
    else:
        cache = "none" if demonstrations is None else "demonstrations"
        if demonstrations is None:
            write_atomically(demo_path, result["demonstrations"].save)
        write_atomically(clone_path, lambda file: th.save(_torch_state(model), file))
    return {
        "cache": cache,
        "transitions": int(result["transitions"]),
        "seconds": round(time.perf_counter() - tic, 2),
        "demonstrations_file": demo_path.name,
        "clone_file": clone_path.name,
    }


def _pretrain_sharded(
    model: Any,
    entry: dict[str, Any],
    env_id: str,
    train_env: Any,
    algo: str,
    folder: Path,
    init_weights: Path | None,
    labelling: dict[str, Any],
) -> dict[str, Any]:
    """:func:`pretrain_trial` with its rounds labelled on an executor and kept one by one (``labelling``)."""
    tic = time.perf_counter()
    init_hash = hashlib.sha256(init_weights.read_bytes()).hexdigest() if init_weights is not None else ""
    expert = make_expert(str(entry["pretrain_from"]), env_id, train_env)  # on-policy bc_coef labels with it
    settings = {**_expert_settings(expert), "labelling": "shards"}
    key = {**demonstrations_key(entry, env_id, algo, init_hash), **settings}
    rounds_folder = folder / f"demonstrations-{_digest(key)[:32]}"
    clone_path = folder / f"clone-{_digest({**clone_key(entry, env_id, algo, init_hash), **settings})[:32]}.pt"
    job = LabellingJob(env_id, dict(entry.get("env_kwargs") or {}), str(entry["pretrain_from"]),
                       expert_factory(env_id)[0], tuple(gym_packages()))  # fmt: skip
    collector = ShardedCollector(model, job, int(labelling.get("seed", 0)), labelling.get("executor", "local"),
                                 int(labelling.get("workers", 1)), labelling.get("address"), rounds_folder)  # fmt: skip
    shards = [collector.path(k, i) for k in range(dagger_arguments(entry)["rounds"]) for i in range(train_env.num_envs)]
    state = _read_clone(clone_path) if all(path.is_file() for path in shards) else None
    steps = int(entry.get("pretrain_steps", PRETRAIN_STEPS))
    critic_steps = entry.get("pretrain_critic_steps")
    if state is not None:
        _load_torch_state(model, state)
        return {"cache": "clone", "transitions": 0, "seconds": round(time.perf_counter() - tic, 2),
                "demonstrations_folder": rounds_folder.name, "clone_file": clone_path.name}  # fmt: skip
    result = behaviour_clone(
        model,
        expert,
        transitions=int(entry.get("pretrain_transitions", key["transitions"])),
        gradient_steps=steps,
        batch_size=int(getattr(model, "batch_size", 256) or 256),
        critic_steps=None if critic_steps is None else int(critic_steps),
        collector=collector,
        **dagger_arguments(entry),
    )
    write_atomically(clone_path, lambda file: th.save(_torch_state(model), file))
    return {
        "cache": "none" if collector.labelled else "demonstrations",
        "rounds_labelled": collector.labelled,
        "transitions": int(result["transitions"]),
        "seconds": round(time.perf_counter() - tic, 2),
        "collect_s": round(result["collect_s"], 2),
        "demonstrations_folder": rounds_folder.name,
        "clone_file": clone_path.name,
    }
