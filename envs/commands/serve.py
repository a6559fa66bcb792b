"""``sb3-graph serve``: run a planner as an edge server (scenes in, one acceleration per vehicle out).

Example::

    sb3-graph serve --planner aim --env CoopIntersection4Way-v0 --port 8765
    sb3-graph evaluate --planner http://127.0.0.1:8765 --scenarios 3 --duration 60

The server binds to loopback (127.0.0.1) unless ``--host`` names another address, which also needs
``--token-file``. Once it listens it prints one line, ``serving <planner> on http://HOST:PORT``, so
that ``--port 0`` (any free port) can be used by scripts. Endpoints, schema and errors: docs/serve.md.
"""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys

from sb3_graph.cli import UserError

DEFAULT_PORT = 8765


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from envs.commands.evaluate import DEFAULT_ENV
    from sb3_graph.commands.arguments import json_object

    parser.add_argument("--planner", required=True, help="planner spec, as evaluate --planner (pr, fifo, aim, "
                        "signal, a model file, a class; '+shield' after it shields it)")  # fmt: skip
    parser.add_argument("--env", default=DEFAULT_ENV, help=f"environment whose layout, policy period and limits "
                        f"the server uses (default: {DEFAULT_ENV})")  # fmt: skip
    parser.add_argument("--env-kwargs", type=json_object, default=None, help="JSON dict passed to gym.make (e.g. "
                        "'{\"config\": {\"max_vehicles\": 100}}'); the clients' environment must match")  # fmt: skip
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default: 127.0.0.1, loopback only; "
                        "any other address needs --token-file)")  # fmt: skip
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default: {DEFAULT_PORT}; 0: any free)")
    parser.add_argument("--shield", action="store_true", help="wrap the planner in the safety shield (per stream)")
    parser.add_argument("--token-file", default=None, help="file whose first line is the token every request "
                        "must carry as 'Authorization: Bearer <token>' (clients: $SB3_GRAPH_TOKEN_FILE)")  # fmt: skip
    parser.add_argument("--max-streams", type=int, default=1000, help="most streams open at once (default: 1000)")
    parser.add_argument("--stream-timeout", type=float, default=600.0,
                        help="seconds after which an unused stream is closed (default: 600)")  # fmt: skip
    parser.add_argument("--max-body", type=int, default=1 << 20, help="largest request body in bytes (default: 1 MiB)")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _check(args: argparse.Namespace):
    """The server's state, built from the arguments (a mistake is a one-line error)."""
    from envs.commands.evaluate import check_env_id
    from envs.planners.loading import is_remote_spec
    from envs.serve.client import read_token

    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be from 0 to 65535, got {args.port}")
    if args.max_streams < 1 or args.stream_timeout <= 0 or args.max_body < 1024:
        raise UserError("--max-streams must be >= 1, --stream-timeout > 0 and --max-body >= 1024")
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        raise UserError("--env-kwargs must be a JSON object")
    if not _is_loopback(args.host) and args.token_file is None:
        raise UserError(f"--host {args.host!r} is not a loopback address: serving beyond it needs --token-file")
    if is_remote_spec(args.planner):
        raise UserError("--planner: a server cannot serve another server's planner; give a local planner spec")
    check_env_id(args.env)
    try:
        token = read_token(args.token_file)
    except ValueError as error:
        raise UserError(f"--token-file: {error}") from None
    from envs.serve.app import PlannerService

    try:
        return PlannerService(args.planner, args.env, args.env_kwargs, shield=args.shield, token=token,
                              max_streams=args.max_streams, stream_timeout=args.stream_timeout,
                              max_body=args.max_body)  # fmt: skip
    except ValueError as error:
        raise UserError(f"--planner: {error}") from None


def run(args: argparse.Namespace) -> int:
    try:
        import uvicorn

        from envs.serve.app import create_app
    except ImportError as error:
        raise UserError(f"the server needs the 'serve' extra (pip install 'sb3-graph[serve]'): {error}") from None
    import torch

    torch.set_num_threads(1)  # one decision at a time: the harness's setting
    service = _check(args)
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    # proto IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets that say they are TCP, and
    # without it every answer waits for the client's delayed ACK (about 40 ms on Linux).
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
        sock.listen(2048)  # before the line below: a client that reads it may connect at once
    except OSError as error:
        sock.close()
        raise UserError(f"--host/--port: cannot bind {args.host}:{args.port} ({error})") from None
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if family == socket.AF_INET6 else host
    config = uvicorn.Config(create_app(service), log_level="warning", access_log=False, timeout_graceful_shutdown=2)
    print(f"serving {service.info()['planner']} on http://{shown}:{port}", flush=True)
    try:
        uvicorn.Server(config).run(sockets=[sock])
    finally:
        sock.close()
    print("server stopped", file=sys.stderr)
    return 0
