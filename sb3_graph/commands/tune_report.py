"""``sb3-graph tune-report``: write the report of an Optuna study (see :mod:`sb3_graph.tuning.report`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_graph.commands import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sb3-graph tune-report``."""
    parser.add_argument("--study-name", required=True, help="the study to report")
    parser.add_argument("--storage", default=None, help="storage URL (default sqlite:///studies/<study-name>.db)")
    parser.add_argument("--out", required=True, help="output folder (must be empty unless --overwrite)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace --out as a whole once the new report is complete"
    )


def run(args: argparse.Namespace) -> int:
    """Run the command: read the study (creating nothing in its storage), then write the report
    into a staged folder that becomes ``--out`` only when complete (``--overwrite``: it replaces the
    old folder as a whole)."""
    import optuna

    from sb3_graph.commands.tune import DEFAULT_STORAGE
    from sb3_graph.files.output_folders import OutputError, staged_folder
    from sb3_graph.tuning.report import check_study, write_report
    from sb3_graph.tuning.storage import make_storage, redact, storage_kind

    url = args.storage or DEFAULT_STORAGE.format(study=args.study_name)
    try:
        storage_kind(url)
    except ValueError as error:
        raise UserError(f"--storage: {error}") from error
    out = Path(args.out)
    empty = out.is_dir() and not out.is_symlink() and not any(out.iterdir())
    if out.exists() and not empty and not args.overwrite:
        raise UserError(f"--out: {str(out)!r} already holds files; choose a new folder or pass --overwrite")
    try:
        storage = make_storage(url, read_only=True)
        names = optuna.get_all_study_names(storage)
    except (ValueError, OSError) as error:  # StorageURLError: unreachable server, missing driver, not a study
        raise UserError(f"--storage: {error}") from None
    if args.study_name not in names:
        raise UserError(f"--study-name: no study {args.study_name!r} in {redact(url)}; studies: {names or 'none'}")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=args.study_name, storage=storage)
    try:
        check_study(study)
    except ValueError as error:
        raise UserError(f"--study-name: {error}") from None
    try:
        with staged_folder(out, overwrite=args.overwrite or empty) as folder:
            written = write_report(study, folder)
    except OutputError as error:
        raise UserError(str(error)) from None
    print(f"sb3-graph tune-report: wrote {len(written)} files to {out}")
    return 0
