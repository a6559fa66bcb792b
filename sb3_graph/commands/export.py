"""``sb3-graph export``: write a model's policy as a weights-only policy file that cannot run code.

Example::

    sb3-graph export runs/4way/best_model.zip planners/4way.safetensors
    sb3-graph export runs/tuned/seed_0/final_model.zip planners/tuned.safetensors --max-nodes 64 --max-edges 1024

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
from pathlib import Path

from sb3_graph.commands import UserError


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
        help="a JSON object stored as the file's planner configuration (header source.planner), read by the "
        "domain that runs the policy, e.g. '{\"residual_base\": \"fullthrottle\", \"residual_scale\": 2.0}' "
        "for a policy trained as a correction of a base planner",
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
        import json

        try:
            config = json.loads(args.planner_config)
        except ValueError as error:
            raise UserError(f"--planner-config: not JSON ({error})") from None
        if not isinstance(config, dict):
            raise UserError(f"--planner-config: must be a JSON object, got {args.planner_config!r}")
        source["planner"] = config
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
