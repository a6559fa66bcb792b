"""User planners named on the command line: ``path/to/file.py:ClassName`` or ``package.module:ClassName``,
and planner servers ``http://HOST:PORT`` (their client, :mod:`envs.serve.client`, registers how they are built).

The class must implement :class:`envs.planners.Planner` and be constructible without arguments.
This imports the user's code, by the user's explicit choice (like ``python file.py``); it is not
a way to open untrusted files.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from urllib.parse import urlsplit

from envs.planners.base import Planner
from envs.simulation import hooks


def is_class_spec(spec: str) -> bool:
    """Whether ``spec`` names a class (``<file.py or module>:<ClassName>``) rather than a baseline or model.

    :param spec: a planner word
    :return: ``True`` for ``something:Name`` where ``Name`` is an identifier
    """
    target, sep, name = str(spec).rpartition(":")
    return bool(sep and target and name.isidentifier())


def _module_of(target: str):
    """Import the module of a class spec: a ``.py`` file (by path) or a dotted module name."""
    if target.endswith(".py"):
        path = Path(target)
        if not path.is_file():
            raise ValueError(f"planner file {target!r} does not exist")
        module_name = f"_sb3_graph_user_planner_{abs(hash(str(path.resolve())))}"
        if module_name in sys.modules:
            return sys.modules[module_name]
        spec = importlib.util.spec_from_file_location(module_name, path)
        if spec is None or spec.loader is None:
            raise ValueError(f"planner file {target!r} cannot be imported")
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module  # dataclasses and pickling look the module up by name
        try:
            spec.loader.exec_module(module)
        except Exception as error:
            del sys.modules[module_name]
            raise ValueError(f"planner file {target!r} failed to import: {type(error).__name__}: {error}") from error
        return module
    try:
        return importlib.import_module(target)
    except ImportError as error:
        raise ValueError(f"planner module {target!r} cannot be imported ({error})") from error


def load_planner_class(spec: str) -> type[Planner]:
    """The class a spec names, checked to be a :class:`Planner`.

    :param spec: ``path/to/file.py:ClassName`` or ``package.module:ClassName``
    :return: the class
    :raises ValueError: a missing file or module, a missing class, or a class that is not a concrete Planner
    """
    target, _, name = str(spec).rpartition(":")
    module = _module_of(target)
    cls = getattr(module, name, None)
    if cls is None:
        raise ValueError(f"planner {spec!r}: {target!r} has no class {name!r}")
    if not (inspect.isclass(cls) and issubclass(cls, Planner)):
        raise ValueError(f"planner {spec!r}: {name!r} is not a subclass of envs.planners.Planner")
    if inspect.isabstract(cls):
        raise ValueError(f"planner {spec!r}: {name!r} is abstract (it does not implement act)")
    return cls


def make_class_planner(spec: str) -> Planner:
    """Build the planner a class spec names (no arguments).

    :param spec: ``path/to/file.py:ClassName`` or ``package.module:ClassName``
    :return: the planner
    :raises ValueError: see :func:`load_planner_class`, or the class needs arguments
    """
    cls = load_planner_class(spec)
    try:
        planner = cls()
    except TypeError as error:
        raise ValueError(f"planner {spec!r}: {cls.__name__}() cannot be built without arguments ({error})") from error
    return planner


def class_planner_name(spec: str) -> str:
    """Report name of a class spec: the planner's own ``name``.

    :param spec: a valid class spec
    :return: the name
    """
    return str(make_class_planner(spec).name)


# ---------------------------------------------------------------------- remote planners
def is_remote_spec(spec: str) -> bool:
    """Whether ``spec`` names a planner server (``http://HOST:PORT``) rather than a local planner.

    :param spec: a planner word (without ``+shield``)
    """
    return str(spec).strip().lower().startswith(("http://", "https://"))


def parse_url(url: str) -> tuple[str, str, int]:
    """Scheme, host and port of ``http://HOST:PORT`` or ``https://HOST:PORT`` (no path, query, user or fragment).

    :param url: the address
    :return: ``(scheme, host, port)``
    :raises ValueError: anything else, naming the part
    """
    parts = urlsplit(str(url).strip())
    if parts.scheme not in ("http", "https"):
        raise ValueError(f"planner server {url!r}: the address must start with http:// or https://")
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username or parts.password:
        raise ValueError(f"planner server {url!r}: give only http://HOST:PORT (no path, query or user)")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"planner server {url!r}: the port must be a number from 1 to 65535") from None
    if not parts.hostname or port is None:
        raise ValueError(f"planner server {url!r}: give both host and port, http://HOST:PORT")
    return parts.scheme, parts.hostname, port


def check_remote_spec(spec: str) -> str:
    """Validate a planner server's address without contacting it.

    :param spec: ``http://HOST:PORT``
    :return: the normalised address
    :raises ValueError: anything but ``http://HOST:PORT``
    """
    scheme, host, port = parse_url(spec)
    return f"{scheme}://{host}:{port}"


def make_remote_planner(spec: str, shielded: bool = False) -> Planner:
    """The planner that plans through the server at ``spec`` (:class:`envs.serve.client.RemotePlanner`,
    registered by :mod:`envs.serve.client` in :mod:`envs.simulation.hooks`).

    :param spec: ``http://HOST:PORT``
    :param shielded: shield it here, in the client (:class:`envs.serve.client.RemoteShield`: a missed
        deadline gets the shield's fallback)
    :raises ValueError: the server cannot be reached or refuses (a wrong token)
    """
    return hooks.maker("remote_planner")(check_remote_spec(spec), shielded=shielded)


def remote_planner_name(spec: str) -> str:
    """Report name of a remote planner, asked from the server: ``<its planner's name>@HOST:PORT``.

    :param spec: ``http://HOST:PORT``
    :raises ValueError: the server cannot be reached or refuses
    """
    return hooks.maker("remote_planner_name")(check_remote_spec(spec))


def model_name(path: Path) -> str:
    """Report name of a model file: ``RL:<folder>`` for ``best_model.zip`` (or ``.safetensors``) and the
    like, else ``RL:<stem>``.

    :param path: the model file
    :return: the name
    """
    stem = path.stem
    if stem in ("best_model", "final_model", "model") and path.parent.name:
        return f"RL:{path.parent.name}"
    return f"RL:{stem}"
