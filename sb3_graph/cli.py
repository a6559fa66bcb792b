"""The ``sb3-graph`` command line.

Each sub-command lives in its own module that provides ``add_arguments(parser)`` and
``run(args) -> int``; this file only dispatches, importing a module when its command runs, so
``sb3_graph`` itself never imports the intersection domain (``envs``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "evaluate": ("envs.commands.evaluate", "compare planners on the same scenarios and write a report"),
    "sweep": ("envs.commands.sweep", "compare planners across traffic demand levels, with their capacity"),
    "train": ("sb3_graph.commands.train", "train a planner from an rl-zoo3 style YAML experiment"),
    "tune": ("sb3_graph.tuning.commands", "tune reward weights and TD3 settings with Optuna"),
    "tune-report": ("sb3_graph.tuning.report_command", "write the report of an Optuna study"),
    "aggregate": ("envs.commands.aggregate", "IQM and 95 % intervals of evaluate reports over seeds and scenarios"),
    "ind": ("envs.commands.ind", "replay inD recordings through the planners"),
    "export": ("sb3_graph.commands.export", "write a model's policy as a weights-only file that cannot run code"),
    "serve": ("envs.commands.serve", "run a planner as an edge server: scenes in, one acceleration per vehicle out"),
}


class UserError(Exception):
    """A mistake in the user's input: printed as one line, no traceback, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """``argparse`` with one-line errors (argparse itself prints the whole usage first)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _load(command: str):
    return importlib.import_module(COMMANDS[command][0])


def build_parser(commands: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser with a sub-parser for each command whose module is importable."""
    parser = _Parser(prog="sb3-graph", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in commands if commands is not None else COMMANDS:
        help_text = COMMANDS[name][1]
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        try:
            module = _load(name)
        except ModuleNotFoundError as error:  # a command whose module is not part of this install
            sub_parser.set_defaults(_missing=str(error))
            continue
        module.add_arguments(sub_parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-graph`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    # Build only the chosen command's parser, so that one command's import cost is not paid by all.
    chosen = [argv[0]] if argv and argv[0] in COMMANDS else None
    parser = build_parser(chosen)
    args = parser.parse_args(argv)
    if getattr(args, "_missing", None):
        parser.error(f"command {args.command!r} is unavailable: {args._missing}")
    try:
        return int(_load(args.command).run(args) or 0)
    except UserError as error:
        print(f"sb3-graph {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sb3-graph {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # `python -m sb3_graph.cli`: run the imported module's main, so that the commands' UserError
    # (sb3_graph.cli.UserError) is the class caught there, not a copy defined in __main__.
    from sb3_graph.cli import main as _main

    sys.exit(_main())
