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
    parser.add_argument("--overwrite", action="store_true", help="replace the report files in --out")


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import optuna

    from sb3_graph.tuning.commands import DEFAULT_STORAGE
    from sb3_graph.tuning.report import write_report
    from sb3_graph.tuning.storage import make_storage, redact, sqlite_path, storage_kind

    url = args.storage or DEFAULT_STORAGE.format(study=args.study_name)
    try:
        kind = storage_kind(url)
    except ValueError as error:
        raise UserError(f"--storage: {error}") from error
    if kind == "sqlite" and not sqlite_path(url).is_file():  # do not create an empty database
        raise UserError(f"--storage: database file {str(sqlite_path(url))!r} does not exist")
    if kind == "journal" and not Path(url[len("journal://") :]).is_file():
        raise UserError(f"--storage: journal file {url[len('journal://') :]!r} does not exist")
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise UserError(f"--out: {str(out)!r} already holds files; choose a new folder or pass --overwrite")
    try:
        storage = make_storage(url)
        names = optuna.get_all_study_names(storage)
    except (ValueError, OSError) as error:  # StorageURLError: unreachable server, missing driver
        raise UserError(f"--storage: {error}") from None
    if args.study_name not in names:
        raise UserError(f"--study-name: no study {args.study_name!r} in {redact(url)}; studies: {names or 'none'}")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=args.study_name, storage=storage)
    written = write_report(study, out)
    print(f"sb3-graph tune-report: wrote {len(written)} files to {out}")
    return 0
