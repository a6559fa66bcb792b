"""``sb3-graph serve``: run a planner as an edge server (scenes in, one acceleration per vehicle out).

Example::

    sb3-graph serve --planner aim --env CoopIntersection4Way-v0 --port 8765
    sb3-graph evaluate --planner http://127.0.0.1:8765 --scenarios 3 --duration 60

The server binds to loopback (127.0.0.1) unless ``--host`` names another address. Every request needs a
token: without ``--token-file``, one is generated at start into a file that only the user may read
(``default_token_path``; the client on the same machine finds it there), and its path is printed. Once it
listens it prints ``serving <planner> on http://HOST:PORT``, so that ``--port 0`` (any free port) can be
used by scripts. Endpoints, schema, errors and the threat model: docs/serve.md.
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import logging
import os
import socket
import sys
from pathlib import Path

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
    parser.add_argument("--shield-bounds", default="none", metavar="BOUNDS",
                        help="the faults the shield is declared to tolerate, as evaluate's --shield-bounds ('none', "
                        "'declared' or KEY=VALUE,...); its latency bound is the oldest scene the server plans (an "
                        "older one is refused with 422 naming 'captured'; none: not limited)")  # fmt: skip
    parser.add_argument("--search-mode", default="async", help="how a lookahead planner searches: async (default: "
                        "beside the steps, in a process of its own; a step answers from the latest finished search) "
                        "or sync (in the step, which waits for it)")  # fmt: skip
    parser.add_argument("--search-workers", type=int, default=None, help="a lookahead planner's processes per "
                        "search, from 1 to the cores (default: the cores but one with --search-mode async, else 1)")
    access = parser.add_argument_group("access")
    access.add_argument("--token-file", default=None, help="file of tokens, one per line, one per client; every "
                        "request must send one as 'Authorization: Bearer <token>' (clients: $SB3_GRAPH_TOKEN_FILE). "
                        "Default: a token generated at start into a file only you may read (its path is printed)")
    access.add_argument("--no-token", action="store_true", help="no token (loopback only; the client is then its "
                        "address): anyone on this machine may command the vehicles")  # fmt: skip
    access.add_argument("--allowed-host", action="append", default=[], metavar="NAME", help="a Host name the server "
                        "answers to besides localhost, 127.0.0.1, ::1 and --host (repeatable; '*': any)")  # fmt: skip
    access.add_argument("--ssl-certfile", default=None, help="TLS: the server's certificate (PEM); clients then use "
                        "https://")  # fmt: skip
    access.add_argument("--ssl-keyfile", default=None, help="TLS: the server's private key (PEM)")
    access.add_argument("--ssl-ca-certs", default=None, help="mutual TLS: CA bundle (PEM) that client certificates "
                        "must be signed by; a client without one is refused")  # fmt: skip
    limits = parser.add_argument_group("limits")
    limits.add_argument("--max-streams", type=int, default=1000, help="most streams open at once (default: 1000)")
    limits.add_argument("--max-streams-per-client", type=int, default=64, help="most streams one client (token, or "
                        "address without token) holds open (default: 64)")  # fmt: skip
    limits.add_argument("--stream-timeout", type=float, default=600.0,
                        help="seconds after which an unused stream is closed, on a timer (default: 600)")  # fmt: skip
    limits.add_argument("--max-body", type=int, default=1 << 20, help="largest request body in bytes (default: 1 MiB)")
    limits.add_argument("--max-connections", type=int, default=None, help="most connections open at once; over it, "
                        "the oldest half-open one is closed (default: 1000, or 64 below the open-file limit)")
    limits.add_argument("--header-timeout", type=float, default=5.0, help="seconds for a request's headers to "
                        "arrive (default: 5)")  # fmt: skip
    limits.add_argument("--body-timeout", type=float, default=10.0, help="seconds for a request's body to arrive "
                        "after its headers (default: 10)")  # fmt: skip
    limits.add_argument("--keep-alive", type=float, default=5.0, help="seconds an idle connection stays open between "
                        "requests (default: 5)")  # fmt: skip
    limits.add_argument("--workers", type=int, default=1, help="planning processes; a stream stays in one; 0: plan on "
                        "the event loop, one decision at a time (default: 1)")  # fmt: skip
    limits.add_argument("--time-limit", type=float, default=1.0, help="seconds a step may take before the client gets "
                        "503 and its worker is killed and replaced (its streams are lost: 404, the client "
                        "reopens); needs --workers >= 1 (default: 1)")  # fmt: skip
    limits.add_argument("--max-restarts", type=int, default=3, help="restarts of one worker allowed within "
                        "--restart-window; past them its slot stays down and new streams go to the other "
                        "workers (default: 3)")  # fmt: skip
    limits.add_argument("--restart-window", type=float, default=60.0, help="seconds of the --max-restarts cap "
                        "(default: 60)")  # fmt: skip
    limits.add_argument("--http", default="auto", help="uvicorn's HTTP parser: auto (httptools when installed, "
                        "else h11), httptools or h11 (default: auto)")  # fmt: skip


# File descriptors the server needs besides its connections (listening socket, workers' sockets, log, libraries).
RESERVED_FDS = 64


def _held_descriptors() -> int:
    """Descriptors this process holds already (0 where the system does not list them)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 0


def connection_cap(requested: int | None, workers: int) -> int:
    """The connection cap: ``requested``, or 1000, kept below the open-file limit less the descriptors
    the process holds already (a server started inside a larger program has fewer to give).

    :raises UserError: ``--max-connections`` at or over what the open-file limit allows
    """
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        soft = soft if soft != resource.RLIM_INFINITY else 1 << 20
    except ImportError:  # not on Unix: no per-process descriptor limit to stay under
        soft = 1 << 20
    room = soft - _held_descriptors() - RESERVED_FDS - 2 * workers
    if room < 8:
        raise UserError(f"the open-file limit ({soft}) is too low for a server: raise it (ulimit -n)")
    if requested is None:
        return min(1000, room)
    if not 1 <= requested <= room:
        raise UserError(f"--max-connections must be from 1 to {room} (the open-file limit {soft} less "
                        f"{soft - room} for the server itself), got {requested}")  # fmt: skip
    return requested


def _check(args: argparse.Namespace):
    """The server's front and planners, built from the arguments (a mistake is a one-line error)."""
    from envs.commands.evaluate import check_env_id, check_search_arguments
    from envs.planners.loading import is_remote_spec
    from envs.serve.access import is_loopback, read_tokens
    from envs.serve.limits import HTTP_PARSERS

    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be from 0 to 65535, got {args.port}")
    if args.max_streams < 1 or args.max_streams_per_client < 1 or args.stream_timeout <= 0 or args.max_body < 1024:
        raise UserError("--max-streams and --max-streams-per-client must be >= 1, --stream-timeout > 0 and "
                        "--max-body >= 1024")  # fmt: skip
    if min(args.header_timeout, args.body_timeout, args.keep_alive, args.time_limit, args.restart_window) <= 0:
        raise UserError("--header-timeout, --body-timeout, --keep-alive, --time-limit and --restart-window must be > 0")
    if min(args.workers, args.max_restarts) < 0:
        raise UserError("--workers and --max-restarts must be >= 0")
    if args.http not in HTTP_PARSERS:
        raise UserError(f"--http must be one of {', '.join(map(repr, HTTP_PARSERS))}, got {args.http!r}")
    if args.http == "httptools" and importlib.util.find_spec("httptools") is None:
        raise UserError("--http httptools: httptools is not installed (pip install 'sb3-graph[serve]')")
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        raise UserError("--env-kwargs must be a JSON object")
    if args.no_token and args.token_file is not None:
        raise UserError("--no-token and --token-file exclude each other")
    if not is_loopback(args.host) and args.token_file is None:
        raise UserError(f"--host {args.host!r} is not a loopback address: serving beyond it needs --token-file")
    if (args.ssl_certfile is None) != (args.ssl_keyfile is None) or (args.ssl_ca_certs and not args.ssl_certfile):
        raise UserError("TLS needs both --ssl-certfile and --ssl-keyfile (and --ssl-ca-certs needs them)")
    for name in ("ssl_certfile", "ssl_keyfile", "ssl_ca_certs"):
        path = getattr(args, name)
        if path is not None and not Path(path).is_file():
            raise UserError(f"--{name.replace('_', '-')}: no file {path!r}")
    check_search_arguments(args)
    if is_remote_spec(args.planner):
        raise UserError("--planner: a server cannot serve another server's planner; give a local planner spec")
    check_env_id(args.env)
    try:
        tokens = read_tokens(args.token_file) if args.token_file is not None else None
    except ValueError as error:
        raise UserError(f"--token-file: {error}") from None
    cap = connection_cap(args.max_connections, args.workers)
    from envs.commands.evaluate import checked_shield_bounds
    from envs.serve.app import PlannerService

    bounds = checked_shield_bounds(args.shield_bounds)
    try:
        service = PlannerService(args.planner, args.env, args.env_kwargs, shield=args.shield, shield_bounds=bounds,
                                 search_mode=args.search_mode, search_workers=args.search_workers)  # fmt: skip
    except ValueError as error:
        raise UserError(f"--planner: {error}") from None
    return service, tokens, cap


def _access(args: argparse.Namespace, tokens: list[str] | None, host: str, port: int):
    """The access rules, once the port is known (the default token file is named after it)."""
    from envs.serve.access import LOOPBACK_HOSTS, Access, default_token_path, write_private_token

    hosts = [*LOOPBACK_HOSTS, *args.allowed_host]
    if host not in ("0.0.0.0", "::"):
        hosts.append(host)
    if tokens is None and not args.no_token:
        path = default_token_path(host, port)
        try:
            tokens = [write_private_token(path)]
        except (OSError, ValueError) as error:
            raise UserError(f"cannot write the token file {str(path)!r} ({error}); give --token-file") from None
        print(f"token file: {path} (clients on this machine find it; elsewhere: SB3_GRAPH_TOKEN_FILE)", flush=True)
    return Access(tokens or [], hosts)


def run(args: argparse.Namespace) -> int:
    try:
        import uvicorn

        from envs.serve.access import Access
        from envs.serve.app import Gateway, tls_context, uvicorn_config
    except ImportError as error:
        raise UserError(f"the server needs the 'serve' extra (pip install 'sb3-graph[serve]'): {error}") from None
    import ssl

    import torch

    torch.set_num_threads(1)  # one decision at a time per process: the harness's setting
    service, tokens, cap = _check(args)
    # Everything built so far (torch, numba, the planners: some 370,000 objects) lives as long as the server: out
    # of the collector's reach, a full collection no longer walks it (about 0.4 s on the development machine, a
    # stall of every stream), and forked workers do not copy its pages by touching them.
    gc.collect()
    gc.freeze()
    # The planning processes are forked now, before the socket exists (they never hold it).
    gateway = Gateway(service, Access([], []), workers=args.workers, max_streams=args.max_streams,
                      max_streams_per_client=args.max_streams_per_client, stream_timeout=args.stream_timeout,
                      max_body=args.max_body, time_limit=args.time_limit, max_restarts=args.max_restarts,
                      restart_window=args.restart_window)  # fmt: skip
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    # proto IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets that say they are TCP, and
    # without it every answer waits for the client's delayed ACK (about 40 ms on Linux).
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
        sock.listen(min(2048, cap))  # before the line below: a client that reads it may connect at once
    except OSError as error:
        sock.close()
        raise UserError(f"--host/--port: cannot bind {args.host}:{args.port} ({error})") from None
    tls = None
    if args.ssl_certfile:  # loaded now, so that a key that does not match its certificate stops the start here
        try:
            tls = tls_context(args.ssl_certfile, args.ssl_keyfile, args.ssl_ca_certs)
        except (ssl.SSLError, OSError) as error:
            sock.close()
            raise UserError(f"--ssl-certfile/--ssl-keyfile/--ssl-ca-certs: {error}") from None
    host, port = sock.getsockname()[:2]
    gateway.access = _access(args, tokens, host, port)
    shown = f"[{host}]" if family == socket.AF_INET6 else host
    config = uvicorn_config(gateway, cap, args.header_timeout, args.body_timeout, args.keep_alive, tls, args.http)
    scheme = "https" if tls else "http"
    print(f"serving {service.info()['planner']} on {scheme}://{shown}:{port}", flush=True)
    try:
        uvicorn.Server(config).run(sockets=[sock])
    except ssl.SSLError as error:
        raise UserError(f"--ssl-certfile/--ssl-keyfile/--ssl-ca-certs: {error}") from None
    finally:
        sock.close()
    logging.getLogger("envs.serve").info("stopped")
    print("server stopped", file=sys.stderr)
    return 0
