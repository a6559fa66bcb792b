"""What every ``sb3-graph`` command shares, for this package's commands and a domain's alike
(see :mod:`sb3_graph.plugins`): the user-error type, argument types and checks, and output staging.

A command module provides ``add_arguments(parser)`` and ``run(args) -> int``; a mistake in the
user's input is a :class:`UserError`, printed as one line naming the field, exit status 2.
"""

from __future__ import annotations


class UserError(Exception):
    """A mistake in the user's input: printed as one line, no traceback, exit status 2."""


from sb3_graph.commands.arguments import check_device, finite_float, json_object  # noqa: E402
from sb3_graph.files.output_folders import OutputError, check_destination, staged_folder, write_file_atomically  # noqa: E402

__all__ = [
    "OutputError",
    "UserError",
    "check_destination",
    "check_device",
    "finite_float",
    "json_object",
    "staged_folder",
    "write_file_atomically",
]
