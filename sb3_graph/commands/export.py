"""``sb3-graph export``: write a model's policy as a weights-only policy file that cannot run code.

Example::

    sb3-graph export runs/4way/best_model.zip planners/4way.safetensors
    sb3-graph export runs/tuned/seed_0/final_model.zip planners/tuned.safetensors --max-nodes 64 --max-edges 1024

A model inside a run folder of ``sb3-graph train`` (``run.json`` and ``config.yml`` beside it, or one
folder up for a checkpoint) gets its planner configuration from the run: the domain of the run's
environment turns the environment's config into what its planner must do again around the policy
(for the intersection: the action's type, scale and glide version, the observation's features), and
the command prints what it stored. ``--planner-config`` replaces that; a ``.safetensors`` input keeps
its own. ``--planner-extra`` adds keys to whichever of these applies (or replaces the same keys), for a
setting that the run's environment does not hold, such as a GNN planner's ``critic_gate``::

    sb3-graph export runs/advice/best_model.zip planners/gated.safetensors --planner-extra '{"critic_gate": 0.2}'

The output holds the policy's tensors (safetensors) and, in the file's metadata, the JSON that
rebuilds it: algorithm, policy class (from an allow-list), policy keyword arguments, observation and
action spaces (see :mod:`sb3_graph.files.policy_files`). ``sb3-graph evaluate --planner`` and ``sb3-graph ind
--planner`` take it like a ``.zip``. The ``.zip`` is read without unpickling; a file that cannot be
read that way is exported only with ``--trust-planner-files`` (SB3's full ``load``, which runs the
pickles in the file: only for files you made yourself). ``--max-nodes``/``--max-edges`` write a
graph policy for larger (or smaller) graphs with the same weights (see
:func:`sb3_graph.files.policy_files.resize_graph_policy`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from sb3_graph.commands import UserError
from sb3_graph.commands.arguments import json_object


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sb3-graph export``."""
    parser.add_argument("model", help="saved model (.zip written by model.save) or a .safetensors policy file")
    parser.add_argument("out", help="the policy file to write (.safetensors; must not exist)")
    parser.add_argument(
        "--trust-planner-files",
        action="store_true",
        help="read the .zip with SB3's full load, which runs the pickled code inside it (your own files only)",
    )
    parser.add_argument(
        "--max-nodes",
        type=int,
        help="write the policy for graphs of up to this many vertices (>= 1; a GNN's weights do not depend on "
        "it: a model trained on a small tuning preset then runs on the full environment)",
    )
    parser.add_argument("--max-edges", type=int, help="likewise for the graph's edges (>= 1)")
    parser.add_argument(
        "--planner-config",
        metavar="JSON",
        type=json_object,
        help="a JSON object stored as the file's planner configuration (header source.planner), read by the "
        "domain that runs the policy, e.g. '{\"residual_base\": \"fullthrottle\", \"residual_scale\": 2.0}' "
        "for a policy trained as a correction of a base planner (default: taken from the run folder that holds "
        "MODEL, by the domain of its environment)",
    )
    parser.add_argument(
        "--planner-extra",
        metavar="JSON",
        type=json_object,
        help="a JSON object whose keys are added to the planner configuration (from --planner-config, the "
        "input file or the run folder), replacing the same keys there, e.g. '{\"critic_gate\": 0.2}'",
    )


def run(args: argparse.Namespace) -> int:
    """Run the command (see the module docstring)."""
    from sb3_graph.files.output_folders import OutputError, write_file_atomically
    from sb3_graph.files.policy_files import SUFFIX, PolicyFileError, load_policy, resize_graph_policy, save_policy

    model, out = Path(args.model), Path(args.out)
    for flag, value in (("--max-nodes", args.max_nodes), ("--max-edges", args.max_edges)):
        if value is not None and value < 1:
            raise UserError(f"{flag}: must be at least 1, got {value}")
    if out.suffix != SUFFIX:
        raise UserError(f"OUT: {str(out)!r} must end with {SUFFIX}")
    if out.exists():
        raise UserError(f"OUT: {str(out)!r} exists; choose a new file name")
    if not model.exists():
        raise UserError(f"MODEL: file not found: {str(model)!r}")
    if not model.is_file():
        raise UserError(f"MODEL: {str(model)!r} is not a file")
    try:
        loaded = load_policy(model, device="cpu", trust=args.trust_planner_files)
    except PolicyFileError as error:
        raise UserError(f"MODEL: {error}") from None
    if args.max_nodes is not None or args.max_edges is not None:
        try:
            loaded = resize_graph_policy(loaded, args.max_nodes, args.max_edges, str(model))
        except PolicyFileError as error:
            raise UserError(f"MODEL: {error}") from None
    description = loaded.description
    source = dict(description.source)
    if args.planner_config is not None:
        source["planner"] = args.planner_config
    elif "planner" not in source:
        found = _run_planner_config(model)
        if found is not None:
            source["planner"] = found[1]
            print(f"sb3-graph export: planner config from {found[0]}: {json.dumps(found[1])}")
    if args.planner_extra is not None:
        source["planner"] = {**dict(source.get("planner") or {}), **args.planner_extra}
        print(f"sb3-graph export: planner config with --planner-extra: {json.dumps(source['planner'])}")
    try:
        write_file_atomically(
            out,
            lambda path: save_policy(loaded.policy, path, description.algorithm, source),
            flag="OUT",
        )
    except (OutputError, PolicyFileError) as error:
        raise UserError(str(error)) from None
    count = sum(int(p.numel()) for p in loaded.policy.parameters())
    print(
        f"sb3-graph export: {description.algorithm} {description.policy_class} ({count:,} parameters) "
        f"from {model} to {out}"
    )
    return 0


def _run_planner_config(model: Path) -> tuple[Path, dict[str, Any]] | None:
    """``(config.yml, planner config)`` from the run folder that holds ``model`` (its folder or the one above,
    for a checkpoint), by the domain of the run's environment (:func:`sb3_graph.plugins.planner_config_factory`);
    ``None`` outside a run folder, or for an environment whose domain declares none. The files are read as
    data (YAML and JSON, no code).

    :raises UserError: a run file that cannot be read, or an environment config that the domain refuses
    """
    from sb3_graph.files.safe_values import UnsafeValueError, load_json, load_yaml, read_text_file
    from sb3_graph.plugins import planner_config_factory
    from sb3_graph.registry import import_object

    for folder in (model.parent, model.parent.parent):
        record_path, config_path = folder / "run.json", folder / "config.yml"
        if record_path.is_file() and config_path.is_file():
            break
    else:
        return None
    try:
        record = load_json(read_text_file(record_path, str(record_path)), str(record_path))
        entry = load_yaml(read_text_file(config_path, str(config_path)), str(config_path))
    except UnsafeValueError as error:
        raise UserError(f"MODEL: {error}; or give --planner-config") from None
    env_id = record.get("env") if isinstance(record, dict) else None
    env_kwargs = entry.get("env_kwargs") if isinstance(entry, dict) else None
    env_config = env_kwargs.get("config", {}) if isinstance(env_kwargs, dict) else {}
    found = planner_config_factory(env_id) if isinstance(env_id, str) else None
    if found is None or not isinstance(env_config, dict):
        return None
    try:
        return config_path, import_object(found[0])(env_config)
    except ValueError as error:
        raise UserError(f"MODEL: {config_path}: {error}; or give --planner-config") from None
