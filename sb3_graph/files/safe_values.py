"""rl-zoo3's Python-valued strings, read without ``eval``.

rl-zoo3 evaluates some values of its YAML files as Python (``policy_kwargs``,
``replay_buffer_class``, ``replay_buffer_kwargs``), so a shared experiment file can run any code
under ``python -m rl_zoo3.train``. ``sb3-graph`` reads the same files, but only this subset:

- literals: numbers, strings, ``True``/``False``/``None``, tuples, lists, dicts (``{"a": 1}``),
  a leading ``-``;
- ``dict(key=value, ...)`` whose values are again of this subset;
- dotted names of classes inside :data:`ALLOWED_PACKAGES`, optionally behind the aliases ``nn``
  (``torch.nn``) and ``th``/``torch`` (``th.nn.ReLU``), or written rl-zoo3's way as
  ``importlib.import_module('package.module').ClassName``.

Anything else (another call, an operator, a name outside the allow-list, an attribute starting
with ``_``, a function or a module instead of a class) is refused with a :class:`UnsafeValueError`
that names the field. Nothing is evaluated: the string is parsed with :func:`ast.parse` and the
tree is walked here. Resolving a name imports at most a module inside the allow-list.
"""

from __future__ import annotations

import ast
import importlib
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import yaml

# Packages whose classes an experiment file may name.
ALLOWED_PACKAGES: tuple[str, ...] = ("sb3_graph", "stable_baselines3", "sb3_contrib", "torch.nn", "torch.optim")
# Leading names that rl-zoo3 files use for torch.
ALIASES: dict[str, str] = {"nn": "torch.nn", "th": "torch", "torch": "torch"}
# Longest string accepted (a policy_kwargs expression is a line or two).
MAX_LENGTH = 10_000
# Limits on a document read from a file that someone else made (docs/security.md).
#: deepest nesting of lists and mappings (experiment entries and metadata need fewer than 10)
MAX_DEPTH = 64
#: most values in one document, counting each use of a YAML alias as a copy ("billion laughs")
MAX_ITEMS = 1_000_000
#: largest text file read whole (experiment files, run records, signatures, metadata)
MAX_TEXT_BYTES = 16 << 20


class UnsafeValueError(ValueError):
    """A value outside the subset that :func:`parse_value` reads (or a name that does not resolve)."""


def read_regular_file(path: str | Path, field: str, max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (FIFOs, devices and sockets are refused
    before they are opened, so that reading never blocks or runs forever).

    :param path: the file (a symbolic link is followed; its target must be a regular file too)
    :param field: the flag or field named in messages
    :param max_bytes: the largest size accepted
    :raises UnsafeValueError: a missing, non-regular, too large or unreadable file
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except OSError as error:
        raise UnsafeValueError(f"{field}: cannot read {str(path)!r} ({error.strerror or error})") from None
    if not stat.S_ISREG(info.st_mode):
        raise UnsafeValueError(f"{field}: {str(path)!r} is not a regular file (a folder, FIFO or device is refused)")
    if info.st_size > max_bytes:
        raise UnsafeValueError(f"{field}: {str(path)!r} is {info.st_size} bytes, more than the {max_bytes} accepted")
    try:
        # O_NONBLOCK: should the file have been swapped for a FIFO since the check, open does not wait
        handle = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(handle, "rb") as file:
            if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
                raise UnsafeValueError(f"{field}: {str(path)!r} is not a regular file")
            data = file.read(max_bytes + 1)
    except OSError as error:
        raise UnsafeValueError(f"{field}: cannot read {str(path)!r} ({error.strerror or error})") from None
    if len(data) > max_bytes:
        raise UnsafeValueError(f"{field}: {str(path)!r} is more than the {max_bytes} bytes accepted")
    return data


def read_text_file(path: str | Path, field: str, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """:func:`read_regular_file` decoded as UTF-8 (a binary file is refused by name)."""
    try:
        return read_regular_file(path, field, max_bytes).decode("utf-8")
    except UnicodeDecodeError:
        raise UnsafeValueError(f"{field}: {str(path)!r} is not a UTF-8 text file") from None


def check_structure(value: Any, field: str, max_depth: int = MAX_DEPTH, max_items: int = MAX_ITEMS) -> Any:
    """Refuse a document nested deeper than ``max_depth`` or holding more than ``max_items`` values.

    Shared parts (YAML aliases) count once per use, so an alias bomb is refused after ``max_items``
    steps instead of being expanded; the walk is iterative (no ``RecursionError``).

    :param value: the parsed document
    :param field: named in messages
    :return: ``value``
    :raises UnsafeValueError: too deep or too large
    """
    stack = [(value, 1)]
    seen = 0
    while stack:
        item, depth = stack.pop()
        seen += 1
        if seen > max_items:
            raise UnsafeValueError(f"{field}: more than {max_items} values (counting each use of a YAML alias)")
        if isinstance(item, dict):
            children = [*item.keys(), *item.values()]
        elif isinstance(item, (list, tuple, set)):
            children = list(item)
        else:
            continue
        if depth > max_depth:
            raise UnsafeValueError(f"{field}: nested more than {max_depth} levels deep")
        stack.extend((child, depth + 1) for child in children)
    return value


def load_yaml(text: str, field: str) -> Any:
    """``yaml.safe_load`` of a document from someone else, with :func:`check_structure`.

    :raises UnsafeValueError: not YAML, nested too deeply or too large (naming ``field``)
    """
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise UnsafeValueError(f"{field}: not valid YAML ({first})") from None
    except RecursionError:
        raise UnsafeValueError(f"{field}: nested more than {MAX_DEPTH} levels deep") from None
    except ValueError as error:  # e.g. a timestamp or number that its constructor cannot read
        raise UnsafeValueError(f"{field}: not valid YAML ({error})") from None
    return check_structure(value, field)


def load_json(text: str | bytes, field: str, constants: bool = True) -> Any:
    """``json.loads`` of a document from someone else, with :func:`check_structure`.

    :param constants: accept Python's ``NaN``, ``Infinity`` and ``-Infinity`` (not JSON, but what
        ``json.dumps`` writes for such floats)
    :raises UnsafeValueError: not JSON, nested too deeply or too large (naming ``field``)
    """

    def constant(name: str) -> Any:
        raise ValueError(f"{name} is not a JSON number")

    try:
        value = json.loads(text, parse_constant=None if constants else constant)
    except RecursionError:
        raise UnsafeValueError(f"{field}: nested more than {MAX_DEPTH} levels deep") from None
    except (TypeError, ValueError) as error:  # JSONDecodeError, UnicodeDecodeError included
        raise UnsafeValueError(f"{field}: not valid JSON ({error})") from None
    return check_structure(value, field)


def finite_number(value: Any) -> bool:
    """A real number (not a bool) that a float holds and that is finite."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float range
        return False


def _within(name: str, packages: tuple[str, ...] = ALLOWED_PACKAGES) -> bool:
    return any(name == package or name.startswith(package + ".") for package in packages)


def resolve_name(dotted: str, field: str, base: type | tuple[type, ...] | None = None) -> type:
    """The class that a dotted name inside :data:`ALLOWED_PACKAGES` names.

    :param dotted: e.g. ``"sb3_graph.GraphPolicy"``, ``"nn.ReLU"``, ``"th.nn.Tanh"``
    :param field: the experiment field, for messages
    :param base: the class must be a subclass of this (or of one of these)
    :return: the class
    :raises UnsafeValueError: a name outside the allow-list, a private part, not a class, not
        importable, or not a subclass of ``base``
    """
    parts = str(dotted).split(".")
    if parts and parts[0] in ALIASES:
        parts = ALIASES[parts[0]].split(".") + parts[1:]
    if not all(part.isidentifier() and not part.startswith("_") for part in parts):
        raise UnsafeValueError(f"{field}: {dotted!r} is not a dotted class name (no private parts)")
    name = ".".join(parts)
    if not _within(name):
        raise UnsafeValueError(
            f"{field}: {dotted!r} is outside the packages an experiment file may name "
            f"({', '.join(ALLOWED_PACKAGES)})"
        )
    value: Any = None
    for cut in range(len(parts), 0, -1):
        module_name = ".".join(parts[:cut])
        if not _within(module_name):
            break
        try:
            value = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name is not None and not module_name.startswith(error.name):
                raise UnsafeValueError(f"{field}: cannot import {dotted!r}: {error}") from None
            continue
        except ImportError as error:
            raise UnsafeValueError(f"{field}: cannot import {dotted!r}: {error}") from None
        for attribute in parts[cut:]:
            if not hasattr(value, attribute):
                raise UnsafeValueError(f"{field}: cannot import {dotted!r}: {module_name} has no {attribute!r}")
            value = getattr(value, attribute)
        break
    else:
        raise UnsafeValueError(f"{field}: cannot import {dotted!r}: no such module")
    if value is None:
        raise UnsafeValueError(f"{field}: cannot import {dotted!r}: no such module")
    if not isinstance(value, type):
        raise UnsafeValueError(f"{field}: {dotted!r} is a {type(value).__name__}, not a class")
    if not _within(getattr(value, "__module__", "") or ""):
        raise UnsafeValueError(
            f"{field}: {dotted!r} is defined in {value.__module__!r}, outside {', '.join(ALLOWED_PACKAGES)}"
        )
    if base is not None and not issubclass(value, base):
        bases = base if isinstance(base, tuple) else (base,)
        expected = " or ".join(f"{b.__module__}.{b.__qualname__}" for b in bases)
        raise UnsafeValueError(f"{field}: {dotted!r} is not a subclass of {expected}")
    return value


def parse_value(text: str, field: str) -> Any:
    """Read one rl-zoo3 Python-valued string (see the module docstring for the subset).

    :param text: e.g. ``"dict(encoder_dim=64, activation_fn=nn.ReLU)"``
    :param field: the experiment field, for messages
    :return: the value (dicts, lists, tuples, literals and classes)
    :raises UnsafeValueError: anything outside the subset, naming the field and the construct
    """
    if not isinstance(text, str):
        raise UnsafeValueError(f"{field}: expected a string, got {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise UnsafeValueError(f"{field}: value longer than {MAX_LENGTH} characters")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as error:
        raise UnsafeValueError(f"{field}: cannot evaluate {text!r}: not a Python expression ({error.msg})") from None
    except (ValueError, RecursionError, MemoryError) as error:  # null bytes, absurd nesting
        raise UnsafeValueError(f"{field}: cannot evaluate {text!r}: {type(error).__name__}") from None
    try:
        return _Reader(field, text).read(tree.body)
    except RecursionError:
        raise UnsafeValueError(f"{field}: cannot evaluate {text!r}: nested too deeply") from None


class _Reader:
    """Walks an expression tree, building the value of the allowed nodes only."""

    def __init__(self, field: str, text: str) -> None:
        self.field = field
        self.text = text

    def refuse(self, what: str) -> UnsafeValueError:
        return UnsafeValueError(
            f"{self.field}: cannot evaluate {self.text!r}: {what} is not allowed "
            "(only literals, dict(...) and dotted class names; sb3-graph never evaluates experiment files)"
        )

    def read(self, node: ast.AST) -> Any:
        if isinstance(node, ast.Constant):
            if isinstance(node.value, (str, int, float, bool, type(None))):
                return node.value
            raise self.refuse(f"the constant {node.value!r}")
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            value = self.read(node.operand)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self.refuse("a sign before a non-number")
            return -value if isinstance(node.op, ast.USub) else value
        if isinstance(node, ast.Tuple):
            return tuple(self.read(item) for item in node.elts)
        if isinstance(node, ast.List):
            return [self.read(item) for item in node.elts]
        if isinstance(node, ast.Dict):
            if any(key is None for key in node.keys):
                raise self.refuse("'**' in a dict")
            keys = [self.read(key) for key in node.keys]
            if not all(isinstance(key, (str, int, float, bool, type(None), tuple)) for key in keys):
                raise self.refuse("a dict key that is not a literal")
            return dict(zip(keys, (self.read(value) for value in node.values)))
        if isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name) and node.func.id == "dict":
                if node.args or any(keyword.arg is None for keyword in node.keywords):
                    raise self.refuse("dict() with positional or '**' arguments")
                return {keyword.arg: self.read(keyword.value) for keyword in node.keywords}
            raise self.refuse(f"the call {ast.unparse(node.func)}(...)")
        if isinstance(node, ast.Attribute):
            return resolve_name(self.dotted(node), self.field)
        if isinstance(node, ast.Name):
            raise self.refuse(f"the bare name {node.id!r}")
        raise self.refuse(f"the expression {type(node).__name__}")

    def dotted(self, node: ast.AST) -> str:
        """``a.b.C`` or ``importlib.import_module('a.b').C`` as ``"a.b.C"``."""
        parts: list[str] = []
        while isinstance(node, ast.Attribute):
            parts.append(node.attr)
            node = node.value
        if isinstance(node, ast.Name):
            parts.append(node.id)
        elif self.is_import_module(node):
            parts.append(node.args[0].value)  # type: ignore[attr-defined]
        else:
            raise self.refuse(f"the expression {ast.unparse(node)!r} before an attribute")
        return ".".join(reversed(parts))

    @staticmethod
    def is_import_module(node: ast.AST) -> bool:
        return (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "importlib"
            and len(node.args) == 1
            and not node.keywords
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        )
