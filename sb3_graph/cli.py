"""The sb3-graph command line: one sub-command per job.

Each sub-command lives in its own module that provides ``add_arguments(parser)`` and
``run(args) -> int``; this file only dispatches, importing a module when its command runs.
:data:`COMMANDS` holds the package's own commands; an installed domain adds its commands through
the ``sb3_graph.commands`` entry point group (:mod:`sb3_graph.plugins`), so ``sb3_graph`` names
no domain package.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from sb3_graph.commands import UserError

# command -> (module, one-line help). A domain's command is a line of the same form in the
# mapping that its `sb3_graph.commands` entry point names (see sb3_graph.plugins).
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("sb3_graph.commands.train", "train a planner from an rl-zoo3 style YAML experiment"),
    "tune": ("sb3_graph.commands.tune", "tune reward weights and algorithm settings with Optuna"),
    "tune-report": ("sb3_graph.commands.tune_report", "write the report of an Optuna study"),
    "export": ("sb3_graph.commands.export", "write a model's policy as a weights-only file that cannot run code"),
}

__all__ = ["COMMANDS", "UserError", "all_commands", "build_parser", "command_parser", "main"]


def all_commands() -> dict[str, tuple[str, str]]:
    """The package's commands, then every installed domain's (a package command keeps its name)."""
    from sb3_graph.plugins import domain_commands

    return {**COMMANDS, **{name: spec for name, spec in domain_commands().items() if name not in COMMANDS}}


class _Parser(argparse.ArgumentParser):
    """``argparse`` with one-line errors (argparse itself prints the whole usage first)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(
    commands: Sequence[str] | None = None,
    table: dict[str, tuple[str, str]] | None = None,
    load: Sequence[str] | None = None,
) -> argparse.ArgumentParser:
    """The argument parser with a sub-parser for each command; a command's module is imported (for its
    arguments) only when it is in ``load``, so that the top-level ``--help`` imports none.

    :param commands: the commands listed (default: all)
    :param table: ``command -> (module, help)`` (default: :func:`all_commands`)
    :param load: the commands whose arguments are added, importing their modules (default: every listed one)
    """
    table = all_commands() if table is None else table
    from sb3_graph import __version__

    names = list(commands if commands is not None else table)
    load = set(names if load is None else load)
    parser = _Parser(prog="sb3-graph", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in names:
        module_name, help_text = table[name]
        # argparse %-formats a help string (not a description): "95 % intervals" must reach it as "95 %% ..."
        sub_parser = sub.add_parser(name, help=help_text.replace("%", "%%"), description=help_text)
        sub_parser.set_defaults(_module=module_name)
        if name not in load:
            continue
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:  # a command whose module is not part of this install
            sub_parser.set_defaults(_missing=str(error))
            continue
        module.add_arguments(sub_parser)
    return parser


def command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The sub-parser of one command (``parser`` itself when it has none of that name).

    :param parser: the parser of :func:`build_parser`
    :param command: a command name
    """
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-graph`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    # Import only the chosen command's module (the top-level --help lists the commands from their
    # one-line helps, importing none); the domains' entry points are read only for a command that
    # is not the package's own.
    table = COMMANDS if argv and argv[0] in COMMANDS else all_commands()
    chosen = [argv[0]] if argv and argv[0] in table else None
    parser = build_parser(chosen, table, load=chosen or [])
    if argv and not argv[0].startswith("-") and argv[0] not in table:
        parser.error(
            f"unknown command {argv[0]!r} (commands: {', '.join(table)}; a domain's commands come from its "
            "installed entry points: run `pip install -e .` in its repository)"
        )
    args, extra = parser.parse_known_args(argv)
    if extra:  # argparse would blame the top-level parser: name the command and its --help instead
        command_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(extra)}")
    args.argv = ["sb3-graph", *argv]  # the command as typed (run records), whoever called main
    if getattr(args, "_missing", None):
        parser.error(f"command {args.command!r} is unavailable: {args._missing}")
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except UserError as error:
        print(f"sb3-graph {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sb3-graph {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # `python -m sb3_graph.cli`: run the imported module's main (one COMMANDS table, not a copy in __main__).
    from sb3_graph.cli import main as _main

    sys.exit(_main())
