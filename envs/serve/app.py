"""The planner server: one planning stream per intersection and client, scenes in, accelerations out.

Built with FastAPI (pydantic models, OpenAPI schema at ``/openapi.json`` and ``/docs``); run by
``sb3-graph serve`` (:mod:`envs.commands.serve`) under uvicorn. Endpoints:

- ``GET /health``: liveness; ``GET /version``: what the server runs (:class:`~envs.serve.schema.ServerInfo`);
- ``POST /streams``: open a stream (its own planner state: AIM's reservations, the shield's plans,
  signal phases), ``201`` with its id;
- ``POST /streams/{id}/step``: a scene (:class:`~envs.serve.schema.SceneIn`) with its sequence number
  ``seq``, answered with one acceleration per vehicle (the same ``seq`` again: the cached answer);
  ``POST /streams/{id}/reset``: a new episode; ``DELETE /streams/{id}``: close;
- ``GET /streams/{id}/ws``: the fast path, a WebSocket that carries the stream's steps as binary frames
  (:mod:`envs.serve.frames`), one answer frame per step.

Two layers: the :class:`Gateway` (the event loop's process) checks every request (``Host``, token,
``Content-Type``, size) and keeps the open streams, whose client owns each, the quotas and the idle
expiry; the :class:`PlannerService` holds the planners of the streams and answers a request's raw body
(:meth:`PlannerService.handle`), in the server's process or in the worker process that the stream was
given to (:mod:`envs.serve.workers`).

Bad input gets a 4xx whose body names the field (:class:`~envs.serve.schema.ErrorReply`), and the
stream and the server go on: 400 an unknown ``Host``, 401 a missing or wrong token, 404 an unknown
stream or path, 405 a wrong method, 409 a ``seq`` out of order, 413 a body over the limit, 415 a body
that is not JSON, 422 a malformed scene (wrong type, unknown field, a key given twice, NaN or infinity, out of
range, impossible size, two vehicles in one place, unknown route, duplicate id, time going back, another
layout, too many vehicles, no ``captured`` time, a ``captured`` time from the future or older than the shield's
latency bound), 429 too many streams or failed tokens, 431 a request head over the limits, 503 no
answer within the time limit.

A scene's age: every step carries ``captured``, the wall-clock time at which the client captured the scene. The
server reads its own clock when it starts planning the step: a ``captured`` more than :data:`CLOCK_SKEW` ahead of
it is refused (422 naming ``captured``: a client clock that runs ahead would make every age look young). With a
shield declared for a latency (``sb3-graph serve --shield --shield-bounds``, :mod:`envs.planners.shield_bounds`),
a scene older than that latency is refused with 422 naming ``captured`` and its age, rather than planned
conservatively: the shield's guarantee holds only within its bounds, and a stale scene gets no command at all
(the vehicles keep their last command, as on a lost answer, and the client sends a fresh scene under the same
``seq``). Without declared latency (``--shield-bounds none``) the age is not limited. A retried step (the same
``seq`` and scene) gets its answer again without a new check.

Every HTTP answer carries ``Server-Timing: app;dur=<ms>``, the server's own time for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import itertools
import json
import math
import os
import secrets
import ssl
import time
from collections import Counter
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from envs.evaluation.harness import env_config
from envs.planners import SHIELD_SUFFIX, check_planner_spec, make_planner, planner_name
from envs.planners.base import Planner
from envs.planners.lookahead import LookaheadPlanner
from envs.planners.shield_bounds import ShieldBounds
from envs.serve import frames
from envs.serve.access import Access, FailureLimit
from envs.serve.handoff import server_frame
from envs.serve.limits import (
    ACCEPT_BURST,
    CONNECTION,
    MAX_HEADER_BYTES,
    ConnectionGuard,
    guarded_protocol,
    guarded_websocket,
    limit_logging,
    uvicorn_protocol,
    websocket_protocol,
)
from envs.serve.schema import (
    ErrorReply,
    Health,
    OpenRequest,
    ResetRequest,
    SceneIn,
    ServerInfo,
    StepReply,
    StreamReply,
)
from envs.serve.wire import SCHEMA_VERSION, SceneBuilder, WireError
from envs.serve.wire import digest as wire_digest
from envs.serve.workers import BEAT, InlinePool, ProcessPool, WorkerGone

# Paths anyone may read without the token (liveness and the schema).
OPEN_PATHS = frozenset({"/health", "/openapi.json", "/docs", "/docs/oauth2-redirect"})
ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 404, 409, 413, 415, 422, 429, 503)}
# Methods whose body must be JSON (refused with 415 before it is read otherwise).
BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})
# Operations that plan (a step over HTTP, a step frame over the WebSocket): under the time limit.
PLANNING = frozenset({"step", "frame"})
# How far a scene's `captured` time may lie ahead of the server's clock before it is refused as from the future [s]:
# the synchronisation error of two clocks (NTP on a LAN: a few ms).
CLOCK_SKEW = 0.05
_wall_clock = time.time  # the clock a scene's age is measured on (tests replace it)


class RequestError(Exception):
    """A refused request: its status, the field and the message (the body of :class:`ErrorReply`)."""

    def __init__(self, status: int, field: str, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.status, self.field, self.message, self.extra = status, field, message, extra


@dataclass
class Stream:
    """One planning stream: its planner (its own state), its clock and its last answer (for a retry)."""

    id: str
    layout: str
    planner: Planner
    steps: int = 0
    last_time: float = -math.inf
    seq: int = 0
    digest: bytes | None = None
    answer: Answer | None = None


@dataclass(frozen=True)
class Answer:
    """A step's answer, kept for a retry: its numbers, the vehicles' ids and accelerations, and what the server's
    shield did (``(overridden, unresolved)``; ``None`` without it)."""

    seq: int
    step: int
    time: float
    ids: np.ndarray
    acc: np.ndarray
    shield: tuple[np.ndarray, bool] | None
    search: dict[str, float] | None = None  # a lookahead's searches beside the steps (search_report)


def _error_body(field_name: str, message: str, **extra: Any) -> bytes:
    return json.dumps({"error": f"{field_name}: {message}", "field": field_name, **extra}).encode()


def _error(status: int, field_name: str, message: str, headers: dict[str, str] | None = None) -> Response:
    return Response(_error_body(field_name, message), status_code=status, media_type="application/json",
                    headers=headers)  # fmt: skip


def _field_of(loc: tuple) -> str:
    """``("body", "vehicles", 3, "speed")`` -> ``"vehicles[3].speed"``."""
    parts = list(loc[1:] if loc and loc[0] == "body" else loc)
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "body"


def _validation_field(error: ValidationError | RequestValidationError) -> tuple[str, str]:
    first = error.errors()[0]
    name = "body" if first.get("type") == "json_invalid" else _field_of(tuple(first.get("loc", ())))
    return name, str(first.get("msg", "invalid"))


def as_served(planner: Any, mode: str = "async", workers: int | None = None, depth: int = 0) -> bool:
    """Set a planner as the server runs it: a ``lookahead`` searches beside the steps (its ``"async"`` mode), so
    that a step answers at glide's cost from the windows of the latest finished search and a search never blocks
    it (nor meets the time limit); ``mode="sync"``: in the step.

    :param mode: how a ``lookahead`` searches (``serve --search-mode``)
    :param workers: its processes per search (``serve --search-workers``; ``None``: the mode's default)
    :return: whether the planner holds a ``lookahead``
    """
    if isinstance(planner, LookaheadPlanner):
        planner.beside_the_steps(mode, workers)
        return True
    inner = getattr(planner, "planner", None)
    return isinstance(inner, Planner) and depth < 8 and as_served(inner, mode, workers, depth + 1)


def search_report(planner: Any) -> dict[str, float] | None:
    """The searches of a stream's ``lookahead`` (started, applied, late, dropped, mismatched, replaced workers,
    the age of the windows in force [s]), or ``None`` for another planner."""
    stats = planner.stats()
    if "lookahead_started" not in stats:
        return None
    return {key.removeprefix("lookahead_"): float(stats[key]) for key in SEARCH_REPORT if key in stats}


def add_searches(total: dict[str, float], report: dict[str, float] | None) -> dict[str, float]:
    """``total`` with one stream's :func:`search_report` (or another total) added: the counts summed, ``age_s_max``
    the largest, ``age_s`` the mean weighted by the searches started (``ahead_s`` likewise)."""
    if not report:
        return total
    started = total.get("started", 0.0) + report.get("started", 0.0)
    for key in ("age_s", "ahead_s"):
        weight = total.get("started", 0.0) * total.get(key, 0.0) + report.get("started", 0.0) * report.get(key, 0.0)
        total[key] = weight / started if started else 0.0
    for key, value in report.items():
        if key == "age_s_max":
            total[key] = max(total.get(key, 0.0), value)
        elif key not in ("age_s", "ahead_s"):
            total[key] = total.get(key, 0.0) + value
    return total


#: the totals of the searches that ``/health`` reports (:class:`~envs.serve.schema.SearchTotals`)
SEARCH_TOTALS = ("started", "applied", "late", "dropped", "mismatched", "expired", "worker_restarts", "age_s",
                 "age_s_max")  # fmt: skip

#: the counters of a ``lookahead`` served beside the steps that a step's JSON answer reports
SEARCH_REPORT = ("lookahead_started", "lookahead_applied", "lookahead_late", "lookahead_dropped",
                 "lookahead_mismatched", "lookahead_expired", "lookahead_worker_restarts", "lookahead_age_s",
                 "lookahead_age_s_max", "lookahead_ahead_s")  # fmt: skip


def _shared_parts(planner: Any, depth: int = 0) -> list[Any]:
    """Parts of a planner that every stream may share: stateless learned planners (their models)."""
    from envs.planners.gnn import GNNPlanner

    if isinstance(planner, GNNPlanner):  # keeps no state between scenes (see GNNPlanner.act_many)
        return [planner]
    inner = getattr(planner, "planner", None)
    return _shared_parts(inner, depth + 1) if isinstance(inner, Planner) and depth < 8 else []


class PlannerService:
    """The planners of the streams: the prototype, the scene builder and each open stream's planner.

    It runs where the planning runs (the server's process, or one worker process per share of the
    streams); the :class:`Gateway` decides which streams exist and who owns them.

    :param spec: planner spec (as ``evaluate --planner``; not a remote one)
    :param env_id: gymnasium id whose configuration (layout, policy period, limits) the server uses
    :param env_kwargs: ``gym.make`` keyword arguments of that environment
    :param shield: wrap the planner in the safety shield (per stream)
    :param shield_bounds: the faults the shield is declared to tolerate (``--shield-bounds``; ``None``: the exact
        world); its ``latency`` limits the age of a scene (a scene captured longer ago is refused; 0: not limited)
    :param search_mode: how a ``lookahead`` searches: ``"async"`` beside the steps (default), ``"sync"`` in them
    :param search_workers: a ``lookahead``'s processes per search (``None``: the cores but one beside the steps)
    """

    def __init__(self, spec: str, env_id: str, env_kwargs: dict[str, Any] | None = None, shield: bool = False,
                 shield_bounds: ShieldBounds | None = None, search_mode: str = "async",
                 search_workers: int | None = None) -> None:  # fmt: skip
        key = check_planner_spec(spec)
        if shield and not key.endswith(SHIELD_SUFFIX):
            key += SHIELD_SUFFIX
        self.spec, self.env_id, self.shield = key, env_id, key.endswith(SHIELD_SUFFIX)
        bounds = shield_bounds or ShieldBounds()
        # The oldest scene planned [s]: the shield's declared latency (None: not limited).
        self.max_scene_age = bounds.latency if self.shield and bounds.latency > 0 else None
        config = env_config(env_id, env_kwargs)
        self.builder = SceneBuilder(config)
        self.prototype = make_planner(key, shield_bounds=shield_bounds)
        self.searches = as_served(self.prototype, search_mode, search_workers)
        check = getattr(self.prototype, "check_capacity", None)
        if check is not None:
            check(int(config["max_vehicles"]), key)
        self._memo_seed = {id(part): part for part in _shared_parts(self.prototype)}
        self._memo_seed[id(self.builder.layout)] = self.builder.layout
        self.streams: dict[str, Stream] = {}
        self.past_searches: dict[str, float] = {}  # the searches of episodes ended (closed, expired, reset streams)
        self.warm_up()

    def new_planner(self) -> Planner:
        """A planner with its own state (a copy of the unused prototype; learned models are shared)."""
        return copy.deepcopy(self.prototype, dict(self._memo_seed))

    def warm_up(self) -> None:
        """One decision on a small scene, the scene also sent as a fast-path frame, so that the first stream does
        not pay for compiling kernels (a first frame compiling them could overrun ``--time-limit``)."""
        lay = self.builder.layout
        cars = [SimpleNamespace(id=i, route=lay.route_names[i], arc=10.0 + 10.0 * i, speed=5.0, length=5.0, width=2.0)
                for i in range(min(2, lay.num_routes))]  # fmt: skip
        planner = self.new_planner()
        planner.reset(0)
        planner.act(self.builder.scene(lay.name, 0.0, cars))
        n = len(cars)
        body = frames.encode_step(1, lay.name, 0.0, lay.route_names, np.arange(n), np.arange(n),
                                  *(np.array([getattr(car, name) for car in cars], float)
                                    for name in ("arc", "speed", "length", "width")))  # fmt: skip
        step = frames.decode_step(body)
        columns = self.builder.table_columns(step.layout, step.routes, step.ids, step.route, step.arc, step.speed,
                                             step.length, step.width)  # fmt: skip
        self.builder.build(0.0, *columns)

    def info(self) -> dict[str, Any]:
        """What the planners are (the server adds its limits): :class:`~envs.serve.schema.ServerInfo`'s fields."""
        from sb3_graph import __version__  # torch: loaded only when asked

        cfg, lay = self.builder.config, self.builder.layout
        return dict(
            package=__version__, schema_version=SCHEMA_VERSION, planner=planner_name(self.spec), spec=self.spec,
            shield=self.shield, env=self.env_id, layout=self.builder.layout.name, dt=self.builder.dt,
            a_min=-float(cfg["max_acceleration"]), a_max=float(cfg["max_acceleration"]),
            max_vehicles=self.builder.limits.max_vehicles, max_speed=self.builder.limits.max_speed,
            max_scene_age=self.max_scene_age,
            routes={name: round(float(length), 2) for name, length in zip(lay.route_names, lay.length)},
        )  # fmt: skip

    def open(self, request: OpenRequest, sid: str | None = None) -> Stream:
        """A new stream (``sid``: its id, given by the gateway; default: a new random one)."""
        if request.layout != self.builder.layout.name:
            raise RequestError(422, "layout", f"this server plans for layout {self.builder.layout.name!r}, "
                                              f"got {request.layout!r}")  # fmt: skip
        if request.dt is not None and abs(request.dt - self.builder.dt) > 1e-9:
            raise RequestError(422, "dt", f"this server's policy period is {self.builder.dt} s, got {request.dt}")
        planner = self.new_planner()
        planner.reset(request.seed)
        stream = Stream(sid or secrets.token_hex(16), request.layout, planner)
        self.streams[stream.id] = stream
        return stream

    def stream(self, sid: str) -> Stream:
        stream = self.streams.get(sid)
        if stream is None:
            raise RequestError(404, "stream", f"no open stream {sid[:40]!r} (closed, expired, or never opened)")
        return stream

    def step(self, sid: str, seq: int, layout: str, time: float, columns: tuple[np.ndarray, ...],
             captured: float) -> Stream:  # fmt: skip
        """One decision, exactly once: ``seq`` one more than the last step's plans; the last step's ``seq``
        again answers what it answered (without planning) if the scene is the same (whichever path carried it).

        :param sid: the stream
        :param seq: the step's sequence number
        :param layout: the scene's layout name
        :param time: its time [s]
        :param columns: ids, route indices (this layout's), arcs, speeds, lengths, widths
        :param captured: when the scene was captured [s since the Unix epoch] (:meth:`check_age`)
        :return: the stream, its last answer (``answer``) that of this step
        :raises RequestError: 409 ``seq`` out of order, 422 a scene the intersection cannot hold, or from the
            future, or older than the shield's latency bound
        """
        stream = self.stream(sid)
        digest = wire_digest(layout, time, columns)
        if seq == stream.seq and stream.answer is not None:
            if stream.digest is not None and digest != stream.digest:
                raise RequestError(409, "seq", f"step {seq} was answered for another scene; a new scene "
                                               f"is step {stream.seq + 1}", expected=stream.seq + 1)  # fmt: skip
            return stream
        if seq != stream.seq + 1:
            retry = f" or {stream.seq} (a retry)" if stream.seq else ""
            raise RequestError(409, "seq", f"expected step {stream.seq + 1}{retry}, got {seq}",
                               expected=stream.seq + 1)  # fmt: skip
        self.check_age(captured)
        if time < stream.last_time:
            raise RequestError(422, "time", f"{time} s is before the stream's last scene "
                                            f"({stream.last_time} s); reset the stream for a new episode")  # fmt: skip
        try:
            scene = self.builder.build(time, *columns)
        except WireError as error:
            raise RequestError(422, error.field, error.message) from None
        planner = stream.planner
        unresolved = getattr(planner, "unresolved", 0)
        acc = np.asarray(planner.act(scene), dtype=float).reshape(-1)
        if acc.shape[0] != scene.num_vehicles or not np.isfinite(acc).all():
            raise RuntimeError(f"the planner answered {acc.shape[0]} accelerations (finite: "
                               f"{bool(np.isfinite(acc).all())}) for {scene.num_vehicles} vehicles")  # fmt: skip
        stream.steps += 1
        stream.last_time = time
        shield = None
        if self.shield:  # what the server's shield did, for the client's counters (the harness reports them)
            shield = (np.asarray(planner.last_overridden, bool).copy(), bool(planner.unresolved > unresolved))
        stream.seq, stream.digest = seq, digest
        stream.answer = Answer(seq, stream.steps, time, scene.vehicle_id, acc, shield,
                               search_report(planner) if self.searches else None)  # fmt: skip
        return stream

    def check_age(self, captured: float) -> None:
        """Refuse a scene captured in the future (beyond :data:`CLOCK_SKEW`) or longer ago than
        :attr:`max_scene_age` (see the module docstring).

        :param captured: when the scene was captured [s since the Unix epoch]
        :raises RequestError: 422 naming ``captured``
        """
        now = _wall_clock()
        age = now - captured
        if age < -CLOCK_SKEW:
            raise RequestError(422, "captured", f"{captured:.3f} is {-age:.3f} s ahead of the server's clock "
                                                f"({now:.3f} s since the epoch): a time from the future (is the "
                                                "client's clock synchronised?)")  # fmt: skip
        if self.max_scene_age is not None and age > self.max_scene_age:
            raise RequestError(422, "captured", f"the scene is {age:.3f} s old, older than the shield's declared "
                                                f"latency bound of {self.max_scene_age:g} s (--shield-bounds): "
                                                "refused, not planned; send a fresh scene")  # fmt: skip

    def json_reply(self, sid: str, answer: Answer) -> bytes:
        """The JSON answer of a step (``json.dumps`` writes each float so that it reads back exactly)."""
        reply = {"stream": sid, "seq": answer.seq, "step": answer.step, "time": answer.time,
                 "ids": answer.ids.tolist(), "accelerations": answer.acc.tolist(), "shield": None}  # fmt: skip
        if answer.shield is not None:
            reply["shield"] = {"overridden": answer.shield[0].tolist(), "unresolved": answer.shield[1]}
        if answer.search is not None:
            reply["search"] = answer.search
        return json.dumps(reply).encode()

    def searches_total(self) -> dict[str, float]:
        """The searches of every stream's ``lookahead`` since the start, the ended episodes' included (empty for
        another planner): :func:`add_searches` of their :func:`search_report`."""
        total = dict(self.past_searches)
        if self.searches:
            for stream in self.streams.values():
                add_searches(total, search_report(stream.planner))
        return total

    def _end_episode(self, stream: Stream | None) -> None:
        """Keep the searches of a stream's episode that ends (a close, an expiry, a reset) in the totals."""
        if stream is not None and self.searches:
            add_searches(self.past_searches, search_report(stream.planner))

    def reset(self, sid: str, request: ResetRequest) -> Stream:
        stream = self.stream(sid)
        self._end_episode(stream)
        stream.planner.reset(request.seed)
        stream.steps, stream.last_time = 0, -math.inf
        stream.seq, stream.digest, stream.answer = 0, None, None
        return stream

    def close(self, sid: str) -> None:
        self._end_episode(self.stream(sid))
        del self.streams[sid]

    def stream_reply(self, stream: Stream) -> dict[str, Any]:
        return {"stream": stream.id, "layout": stream.layout, "dt": self.builder.dt, "steps": stream.steps}

    def handle(self, op: str, sid: str, body: bytes) -> tuple[int, bytes]:
        """A request as bytes: ``op`` (``open``, ``step``, ``frame``, ``reset``, ``close``) on stream ``sid`` with
        the raw ``body`` (JSON; ``frame``: a fast-path step frame, :mod:`envs.serve.frames`); the answer's status
        and body (JSON; for ``frame``, an answer or refusal frame). Refusals name the field.
        """
        if op == "frame":
            return self._frame(sid, body)
        try:
            if op == "step":
                # pydantic's own JSON parser: about half the time of json.loads plus validation
                scene = SceneIn.model_validate_json(body)
                _unique_keys(body)
                try:
                    columns = self.builder.columns(scene.layout, scene.vehicles)
                except WireError as error:
                    raise RequestError(422, error.field, error.message) from None
                stream = self.step(sid, scene.seq, scene.layout, scene.time, columns, scene.captured)
                return 200, self.json_reply(sid, stream.answer)
            if op == "open":
                request = OpenRequest.model_validate_json(body)
                _unique_keys(body)
                return 201, json.dumps(self.stream_reply(self.open(request, sid))).encode()
            if op == "reset":
                request = ResetRequest.model_validate_json(body)
                _unique_keys(body)
                return 200, json.dumps(self.stream_reply(self.reset(sid, request))).encode()
            if op == "close":
                self.close(sid)
                return 204, b""
            if op == "expire":
                self._end_episode(self.streams.pop(sid, None))
                return 204, b""
            if op == "searches":
                return 200, json.dumps(self.searches_total()).encode()
        except ValidationError as error:
            return 422, _error_body(*_validation_field(error))
        except RequestError as error:
            return error.status, _error_body(error.field, error.message, **error.extra)
        raise ValueError(f"unknown operation {op!r}")

    def _frame(self, sid: str, body: bytes) -> tuple[int, bytes]:
        """A fast-path step: decoded and checked by :mod:`envs.serve.frames` (msgspec, vectorized), answered as a
        frame."""
        try:
            step = frames.decode_step(body)
            columns = self.builder.table_columns(step.layout, step.routes, step.ids, step.route, step.arc,
                                                 step.speed, step.length, step.width)  # fmt: skip
        except WireError as error:
            return 422, frames.encode_error(422, error.field, error.message)
        try:
            answer = self.step(sid, step.seq, step.layout, step.time, columns, step.captured).answer
        except RequestError as error:
            return error.status, frames.encode_error(error.status, error.field, error.message,
                                                     error.extra.get("expected"))  # fmt: skip
        shield = answer.shield or (None, None)
        return 200, frames.encode_reply(answer.seq, answer.step, answer.time, answer.ids, answer.acc, *shield)


class _DuplicateKey(ValueError):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        raise _DuplicateKey(next(key for key in keys if keys.count(key) > 1))
    return dict(pairs)


def _unique_keys(body: bytes) -> None:
    """Refuse a JSON body in which an object names a key twice (pydantic, as JSON parsers do, keeps the last).

    :raises RequestError: 422 naming the key
    """
    try:
        json.loads(body, object_pairs_hook=_no_duplicates)
    except _DuplicateKey as error:
        key = str(error)[:64]
        raise RequestError(422, key, f"the key {key!r} appears twice in one object; each key may appear "
                                     "once") from None  # fmt: skip


@dataclass
class _Handed:
    """A stream's WebSocket handed to the worker that plans the stream (:mod:`envs.serve.handoff`): the event loop
    keeps the connection open and counted but reads nothing more from it.

    :param key: the server's number for the connection
    :param worker: the worker that serves it
    :param sid: its stream
    :param connection: uvicorn's protocol object of the connection
    :param done: set when the connection is over (the worker closed it, or the stream was dropped)
    """

    key: int
    worker: int
    sid: str
    connection: Any
    done: asyncio.Future

    def end(self) -> None:
        """The connection is over: its endpoint returns, and uvicorn closes the event loop's end."""
        if not self.done.done():
            self.done.set_result(None)


def _lost_stream() -> RequestError:
    return RequestError(404, "stream", "lost (its planning process ended); open a new one")


@dataclass
class _Entry:
    """An open stream as the gateway knows it: the worker that plans it, its client, its last use."""

    worker: int
    client: str
    last_used: float = field(default_factory=time.monotonic)


class Gateway:
    """The server's front: who may ask (:class:`~envs.serve.access.Access`), which streams are open and whose,
    the quotas, the idle expiry and the time limit; the planning itself is ``pool``'s.

    :param service: the planners (and what the server runs, for ``/version``)
    :param access: tokens and ``Host`` names
    :param workers: planning processes (0: plan on the event loop, one decision at a time)
    :param max_streams: most streams open at once
    :param max_streams_per_client: most streams one client holds
    :param stream_timeout: a stream unused for this long [s] is closed (checked on a timer)
    :param max_body: largest request body [bytes]
    :param time_limit: a step not answered within this many seconds gets 503, and its worker is killed and
        replaced (its streams are lost: 404, the client reopens); needs ``workers >= 1`` (in the server's
        process a step is not timed)
    :param max_restarts: restarts of one worker slot allowed within ``restart_window`` seconds; past them
        the slot stays down and new streams go to the other workers
    :param restart_window: the window of the restart cap [s]
    """

    def __init__(
        self,
        service: PlannerService,
        access: Access,
        workers: int = 0,
        max_streams: int = 1000,
        max_streams_per_client: int = 64,
        stream_timeout: float = 600.0,
        max_body: int = 1 << 20,
        time_limit: float = 1.0,
        max_restarts: int = 3,
        restart_window: float = 60.0,
    ) -> None:
        self.service, self.access = service, access
        self.pool: InlinePool | ProcessPool = (
            ProcessPool(service, workers, max_restarts, restart_window) if workers > 0 else InlinePool(service)
        )
        self.pool.on_exit = self._lost
        self.workers = int(workers)
        self.max_streams, self.max_streams_per_client = int(max_streams), int(max_streams_per_client)
        self.stream_timeout, self.max_body, self.time_limit = float(stream_timeout), int(max_body), float(time_limit)
        self.streams: dict[str, _Entry] = {}
        self.per_client: Counter[str] = Counter()
        self.expired = 0
        self.lost = 0  # streams lost with their worker
        self.failures = FailureLimit()  # failed authentications per source address
        self.sockets: dict[str, Any] = {}  # each stream's WebSocket (the fast path), at most one
        self.handed: dict[int, _Handed] = {}  # the WebSockets handed to workers, by key
        self._keys = itertools.count(1)
        self._overran: set[int] = set()  # workers stopped by the time limit while planning a handed connection's step
        self.pool.on_closed = self._handed_closed
        self._info = service.info()

    async def searches(self) -> dict[str, float] | None:
        """The searches of the planning processes' ``lookahead`` streams since the start (``None``: the planner
        searches nothing). A process that does not answer within the time limit (it plans a long step) is left out
        of this answer; its streams' searches are counted again in the next."""
        if not self.service.searches:
            return None
        total: dict[str, float] = {}
        for worker in range(self.pool.size):
            if not self.pool.alive(worker):
                continue
            with contextlib.suppress(TimeoutError, WorkerGone, ValueError):
                status, body = await self.pool.call(worker, "searches", "", b"", self.time_limit)
                if status == 200:
                    add_searches(total, json.loads(body))
        return {key: total.get(key, 0.0) for key in SEARCH_TOTALS}

    def info(self) -> dict[str, Any]:
        limits = {"max_streams": self.max_streams, "max_streams_per_client": self.max_streams_per_client}
        return ServerInfo(**self._info, **limits, workers=self.workers).model_dump()

    async def _call(self, worker: int, op: str, sid: str, body: bytes) -> tuple[int, bytes]:
        try:
            return await self.pool.call(worker, op, sid, body, self.time_limit if op in PLANNING else None)
        except TimeoutError:
            # a scene that overran must not hold its worker: it is killed and replaced, its streams lost (a handed
            # connection's step it was planning meanwhile gets 503 too)
            self._overran.add(worker)
            self.pool.stop(worker)
            raise self._overrun() from None
        except WorkerGone:
            self._drop(sid)
            raise _lost_stream() from None

    def _overrun(self) -> RequestError:
        return RequestError(503, "time_limit", f"no answer within {self.time_limit} s; its planning process was "
                                               "stopped and this stream is lost: open a new one")  # fmt: skip

    def _lost(self, worker: int) -> None:
        """The worker ``worker`` ended: its streams are gone with it (their next request gets 404; a handed
        connection whose step it was planning gets that step's refusal, then a close)."""
        if self.pool.hands:
            since, key = self.pool.planning(worker)
            handed = self.handed.get(key) if since > 0 else None
            if handed is not None and handed.worker == worker:
                error = self._overrun() if worker in self._overran else _lost_stream()
                refusal = frames.encode_error(error.status, error.field, error.message)
                handed.connection.transport.write(server_frame(refusal))
        self._overran.discard(worker)
        gone = [sid for sid, entry in self.streams.items() if entry.worker == worker]
        for sid in gone:
            self._drop(sid)
        self.lost += len(gone)

    def _drop(self, sid: str) -> None:
        entry = self.streams.pop(sid, None)
        if entry is not None:
            self.per_client[entry.client] -= 1
            self.pool.load[entry.worker] -= 1
        socket = self.sockets.pop(sid, None)
        if socket is not None:  # a closed, expired or lost stream keeps no connection open
            self._close(socket)

    def _close(self, socket: Any) -> None:
        """Close a stream's WebSocket: on the event loop, or (handed) by its worker, and the event loop's end."""
        if isinstance(socket, _Handed):
            self.pool.release(socket.worker, socket.key, socket.sid)
            socket.end()
        else:
            asyncio.get_running_loop().create_task(_close_socket(socket))

    def _handed_closed(self, key: int) -> None:
        """The worker closed the handed connection ``key`` (the client closed it, went, or broke the protocol)."""
        handed = self.handed.get(key)
        if handed is not None:
            handed.end()

    def _hand(self, connection: Any, entry: _Entry, sid: str) -> _Handed | None:
        """Hand the upgraded ``connection`` to the worker of stream ``sid``; ``None``: it stays on the event loop
        (bytes came before the hand-over, or the worker could not take it)."""
        fd = connection.detach()
        if fd is None:
            return None
        key = next(self._keys)
        # Registered before the hand-over: from then on the worker may answer the client's steps before this
        # thread runs again (an in-process server under load: the client saw answers, `handed` still empty)
        done = asyncio.get_running_loop().create_future()
        handed = self.handed[key] = _Handed(key, entry.worker, sid, connection, done)
        try:
            passed = self.pool.hand(entry.worker, key, sid, fd, self.max_body)
        finally:
            os.close(fd)
        if not passed:
            del self.handed[key]
            connection.transport.resume_reading()
            return None
        connection.on_lost = handed.end  # the server shuts down
        return handed

    async def open(self, client: str, body: bytes) -> tuple[int, bytes]:
        if len(self.streams) >= self.max_streams:
            raise RequestError(429, "streams", f"{len(self.streams)} streams are open, the most this server "
                                               "takes; close one first")  # fmt: skip
        if self.per_client[client] >= self.max_streams_per_client:
            raise RequestError(429, "streams", f"this client holds {self.per_client[client]} streams, the most one "
                                               "client may; close one first")  # fmt: skip
        alive = [k for k in range(self.pool.size) if self.pool.alive(k)]
        if not alive:
            raise RequestError(503, "server", "no planning process is running (being replaced, or each past its "
                                               "restart cap); try again")
        worker = min(alive, key=lambda k: self.pool.load[k])
        sid = secrets.token_hex(16)
        # counted before the worker answers: concurrent opens cannot overrun the quotas
        self.streams[sid] = _Entry(worker, client)
        self.per_client[client] += 1
        self.pool.load[worker] += 1
        try:
            status, payload = await self._call(worker, "open", sid, body)
        except BaseException:
            self._drop(sid)
            raise
        if status != 201:
            self._drop(sid)
        return status, payload

    async def forward(self, client: str, op: str, sid: str, body: bytes) -> tuple[int, bytes]:
        """A request on an open stream of this client (another client's stream is unknown to it: 404)."""
        entry = self.streams.get(sid)
        if entry is None or entry.client != client:
            raise RequestError(404, "stream", f"no open stream {sid[:40]!r} (closed, expired, or never opened)")
        entry.last_used = time.monotonic()
        status, payload = await self._call(entry.worker, op, sid, body)
        if op == "close" and status == 204:
            self._drop(sid)
        return status, payload

    async def socket(self, websocket: Any, sid: str) -> None:
        """Serve a stream's steps over a WebSocket until the client closes it: each binary message a step frame,
        each answer a frame (a refusal too; the connection stays open). Only the stream's own client may open it
        (another's, or an unknown stream: the upgrade is refused, 403)."""
        client = websocket.scope.get("state", {}).get("client", "")
        entry = self.streams.get(sid)
        if entry is None or entry.client != client:
            await websocket.close(code=4404, reason="stream")
            return
        # A plain connection goes to the stream's worker (envs.serve.handoff): nothing is read from it here after
        # the upgrade's answer
        connection = websocket.scope.get("extensions", {}).get(CONNECTION) if self.pool.hands else None
        if connection is not None and not connection.hold():
            connection = None
        await websocket.accept()
        # One socket per stream (so a client's sockets are bounded by its stream quota): a new one replaces the old
        old, self.sockets[sid] = self.sockets.get(sid), websocket
        if old is not None:
            self._close(old)
        handed = None
        if connection is not None:
            if self.streams.get(sid) is not entry:  # closed or lost meanwhile
                self.sockets.pop(sid, None)
                return
            handed = self._hand(connection, entry, sid)
        if handed is not None:
            self.sockets[sid] = handed
            try:
                await handed.done
            finally:
                del self.handed[handed.key]
                if self.sockets.get(sid) is handed:
                    del self.sockets[sid]
            return
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                data = message.get("bytes")
                if data is None:
                    payload = frames.TEXT_REFUSAL
                else:
                    try:
                        _, payload = await self.forward(client, "frame", sid, data)
                    except RequestError as error:
                        payload = frames.encode_error(error.status, error.field, error.message,
                                                      error.extra.get("expected"))  # fmt: skip
                await websocket.send({"type": "websocket.send", "bytes": payload})
        except (WebSocketDisconnect, RuntimeError, OSError):  # the client went, or the socket was replaced
            return
        finally:
            if self.sockets.get(sid) is websocket:
                del self.sockets[sid]

    async def expire(self) -> int:
        """Close the streams unused for longer than ``stream_timeout``; how many."""
        now = time.monotonic()
        idle = [sid for sid, entry in self.streams.items() if now - entry.last_used > self.stream_timeout]
        for sid in idle:  # a handed connection's steps are seen by its worker only: when was its last?
            handed = self.sockets.get(sid)
            if isinstance(handed, _Handed):
                with contextlib.suppress(Exception):
                    _, last = await self.pool.call(handed.worker, "last_used", sid, b"", None)
                    self.streams[sid].last_used = max(self.streams[sid].last_used, float(last))
        now = time.monotonic()
        idle = [sid for sid in idle if sid in self.streams and now - self.streams[sid].last_used > self.stream_timeout]
        for sid in idle:
            worker = self.streams[sid].worker
            self._drop(sid)
            with contextlib.suppress(Exception):
                await self.pool.call(worker, "expire", sid, b"", None)
        self.expired += len(idle)
        return len(idle)

    async def watch_forever(self) -> None:
        """The time limit of the handed connections' steps, which their worker reads and plans unseen by the
        event loop: every tenth of ``time_limit`` (at most 0.25 s), a worker planning one step for longer, or
        holding handed connections with its loop stopped for longer (a ``SIGSTOP``, a hang between steps), is
        stopped; the connection of the step it was planning gets 503 (:meth:`_lost`), its streams are lost."""
        if not self.pool.hands:
            return
        period = min(max(self.time_limit / 10, 0.01), 0.25)
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            holding = {handed.worker for handed in self.handed.values()}
            for worker in range(self.pool.size):
                if worker in self._overran or not self.pool.alive(worker):
                    continue
                since, _ = self.pool.planning(worker)
                if since > 0:
                    stuck = now - since > self.time_limit
                else:
                    stuck = worker in holding and now - self.pool.heartbeat(worker) > self.time_limit + BEAT
                if stuck:
                    self._overran.add(worker)
                    self.pool.stop(worker)

    async def expire_forever(self) -> None:
        """The idle expiry's timer: every quarter of ``stream_timeout`` (at most 5 s)."""
        period = min(max(self.stream_timeout / 4, 0.05), 5.0)
        while True:
            await asyncio.sleep(period)
            await self.expire()


async def _close_socket(websocket: Any) -> None:
    with contextlib.suppress(Exception):  # already closing or closed
        await websocket.close(code=1000)


class _Guard:
    """ASGI middleware: the ``Host`` check, the token (failures rate-limited per source), JSON only, the body limit,
    all before any parsing; a WebSocket's upgrade passes the same ``Host`` and token checks.

    :param app: the application
    :param gateway: the server's front (its access rules and body limit)
    """

    def __init__(self, app, gateway: Gateway) -> None:
        self.app, self.gateway = app, gateway

    def _refusal(self, scope, headers: dict[bytes, bytes]) -> tuple[int, str, str, dict[str, str] | None] | None:
        """Why a request or upgrade is refused (status, field, message, headers), ``None`` if it may pass."""
        access = self.gateway.access
        if not access.host_allowed(headers.get(b"host")):
            return 400, "host", "this server does not answer to that Host name (see --allowed-host)", None
        if scope["path"] in OPEN_PATHS:
            return None
        peer = (scope.get("client") or ("unknown", 0))[0]
        limit = self.gateway.failures
        if limit.over(peer) and headers.get(b"authorization") is None:  # a flood without a token: not even parsed
            limit.failure(peer)
            return 429, "authorization", "too many failed authentications from this address; slow down", None
        client = access.client(headers.get(b"authorization"), peer)
        if client is None:
            if not limit.failure(peer):
                return 429, "authorization", "too many failed authentications from this address; slow down", None
            return (401, "authorization", "missing or wrong token (send 'Authorization: Bearer <token>')",
                    {"WWW-Authenticate": "Bearer"})  # fmt: skip
        scope.setdefault("state", {})["client"] = client
        return None

    async def __call__(self, scope, receive, send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = dict(scope["headers"])
        refused = self._refusal(scope, headers)
        if kind == "websocket":
            if refused is not None:  # before the upgrade is accepted: uvicorn answers 403 and closes
                await receive()
                return await send({"type": "websocket.close", "code": 1008, "reason": refused[1]})
            return await self.app(scope, receive, send)
        if refused is None and scope["method"] in BODY_METHODS:
            kind = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
            if kind != b"application/json":
                refused = (415, "content-type", "the body must be JSON (Content-Type: application/json)", None)
        if refused is not None:
            return await _error(*refused)(scope, receive, send)
        limit = self.gateway.max_body
        declared = headers.get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            return await _error(413, "body", f"the body is over the limit of {limit} bytes")(scope, receive, send)
        body, more = b"", True
        while more:  # read it all here (bounded), then hand it on
            message = await receive()
            if message["type"] != "http.request":
                return await self.app(scope, _replay([message]), send)
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > limit:
                return await _error(413, "body", f"the body is over the limit of {limit} bytes")(scope, receive, send)
        tic = time.perf_counter()

        async def timed_send(message) -> None:
            # Server-Timing: the server's own wall time for the request after its body arrived (parsing,
            # scene building, planning, the answer's encoding), for clients and benchmarks to tell it apart
            if message["type"] == "http.response.start":
                took = f"app;dur={(time.perf_counter() - tic) * 1e3:.3f}".encode()
                message = {**message, "headers": [*message.get("headers", []), (b"server-timing", took)]}
            await send(message)

        whole = _replay([{"type": "http.request", "body": body, "more_body": False}], receive)
        await self.app(scope, whole, timed_send)


def _replay(messages: list[dict], then=None):
    async def receive():
        if messages:
            return messages.pop(0)
        return await then() if then is not None else {"type": "http.disconnect"}

    return receive


def _body_schema(model: type[BaseModel]) -> dict[str, Any]:
    ref = {"$ref": f"#/components/schemas/{model.__name__}"}
    return {"requestBody": {"content": {"application/json": {"schema": ref}}, "required": True}}


def create_app(gateway: Gateway) -> FastAPI:
    """The FastAPI application around a :class:`Gateway`.

    :param gateway: the server's front and its planners
    :return: the ASGI application (uvicorn runs it)
    """

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        await gateway.pool.start()
        expiry = asyncio.get_running_loop().create_task(gateway.expire_forever())
        watch = asyncio.get_running_loop().create_task(gateway.watch_forever())
        try:
            yield
        finally:
            expiry.cancel()
            watch.cancel()
            await gateway.pool.close()

    app = FastAPI(
        title="sb3-graph planner server",
        version=str(SCHEMA_VERSION),
        description="Scenes of a cooperative intersection in, one acceleration per vehicle out (see docs/serve.md).",
        lifespan=lifespan,
    )
    app.state.gateway = gateway

    @app.exception_handler(RequestError)
    async def _refused(request: Request, error: RequestError) -> Response:
        return Response(_error_body(error.field, error.message, **error.extra), status_code=error.status,
                        media_type="application/json")  # fmt: skip

    @app.exception_handler(RequestValidationError)
    async def _malformed(request: Request, error: RequestValidationError) -> Response:
        return _error(422, *_validation_field(error))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, error: StarletteHTTPException) -> Response:
        name = {404: "path", 405: "method"}.get(error.status_code, "body")
        return _error(error.status_code, name, f"{request.method} {request.url.path[:80]}: {error.detail}",
                      headers=getattr(error, "headers", None))  # fmt: skip

    def client_of(request: Request) -> str:
        return request.scope.get("state", {}).get("client", "")

    def answer(status: int, payload: bytes) -> Response:
        return Response(payload or None, status_code=status, media_type="application/json" if payload else None)

    @app.get("/health", response_model=Health)
    async def health() -> dict[str, Any]:
        return {"status": "ok", "streams": len(gateway.streams), "workers": gateway.pool.alive_count(),
                "restarts": gateway.pool.restarts, "lost_streams": gateway.lost,
                "searches": await gateway.searches()}  # fmt: skip

    @app.get("/version", response_model=ServerInfo, responses=ERRORS)
    async def version() -> dict[str, Any]:
        return gateway.info()

    @app.post("/streams", response_model=StreamReply, status_code=201, responses=ERRORS,
              openapi_extra=_body_schema(OpenRequest))  # fmt: skip
    async def open_stream(request: Request) -> Response:
        return answer(*await gateway.open(client_of(request), await request.body()))

    @app.post("/streams/{stream}/step", response_model=StepReply, responses=ERRORS,
              openapi_extra=_body_schema(SceneIn))  # fmt: skip
    async def step(stream: str, request: Request) -> Response:
        return answer(*await gateway.forward(client_of(request), "step", stream, await request.body()))

    @app.post("/streams/{stream}/reset", response_model=StreamReply, responses=ERRORS,
              openapi_extra=_body_schema(ResetRequest))  # fmt: skip
    async def reset(stream: str, request: Request) -> Response:
        return answer(*await gateway.forward(client_of(request), "reset", stream, await request.body()))

    @app.delete("/streams/{stream}", status_code=204, responses=ERRORS)
    async def close(stream: str, request: Request) -> Response:
        return answer(*await gateway.forward(client_of(request), "close", stream, b""))

    @app.websocket("/streams/{stream}/ws")
    async def step_socket(websocket: WebSocket, stream: str) -> None:
        """The fast path: the stream's steps as binary frames (:mod:`envs.serve.frames`) over one connection."""
        await gateway.socket(websocket, stream)

    base_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        """FastAPI's schema, plus the request bodies (parsed by the planners, not by FastAPI), this server's
        enums and limits, and the bearer token."""
        if app.openapi_schema is None:
            app.openapi_schema = _document(base_openapi(), gateway)
        return app.openapi_schema

    app.openapi = openapi
    app.add_middleware(_Guard, gateway=gateway)
    return app


def _document(schema: dict[str, Any], gateway: Gateway) -> dict[str, Any]:
    """Complete FastAPI's schema: the bodies' models, enums of this server's layout and routes, its
    ``max_vehicles`` as ``maxItems``, and the bearer-token security scheme on every path but :data:`OPEN_PATHS`."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in (SceneIn, OpenRequest, ResetRequest):
        body = model.model_json_schema(ref_template="#/components/schemas/{model}")
        components.update(body.pop("$defs", {}))
        components[model.__name__] = body
    layout = gateway.service.builder.layout
    components["SceneIn"]["properties"]["layout"]["enum"] = [layout.name]
    components["SceneIn"]["properties"]["vehicles"]["maxItems"] = gateway.service.builder.limits.max_vehicles
    components["OpenRequest"]["properties"]["layout"]["enum"] = [layout.name]
    components["Vehicle"]["properties"]["route"]["enum"] = list(layout.route_names)
    if gateway.access.tokens:
        schema["components"]["securitySchemes"] = {"bearer": {"type": "http", "scheme": "bearer",
                                                              "description": "a token of the server's token file"}}
        schema["security"] = [{"bearer": []}]
        for path, operations in schema.get("paths", {}).items():
            if path in OPEN_PATHS:
                for operation in operations.values():
                    operation["security"] = []
    return schema


def tls_context(certfile: str, keyfile: str, ca_certs: str | None = None) -> ssl.SSLContext:
    """The server's TLS settings: its certificate and key, and with ``ca_certs`` a client certificate required
    (mutual TLS).

    :raises ssl.SSLError: a key that does not match the certificate, or an unreadable file
    :raises OSError: a file that cannot be read
    """
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(certfile, keyfile)
    if ca_certs:
        context.load_verify_locations(ca_certs)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def uvicorn_config(
    gateway: Gateway,
    max_connections: int = 1000,
    header_timeout: float = 5.0,
    body_timeout: float = 10.0,
    keep_alive: float = 5.0,
    tls: ssl.SSLContext | dict[str, Any] | None = None,
    http: str = "auto",
):
    """uvicorn's settings for a :class:`Gateway`: the guarded HTTP and WebSocket protocols (connection cap from
    the accept, TLS handshake, header and body read timeouts, header limits, :mod:`envs.serve.limits`),
    ``limit_concurrency`` just above the cap, the keep-alive timeout.

    :param gateway: the server's front
    :param max_connections: most connections open at once (below the open-file limit)
    :param header_timeout: seconds for the TLS handshake and a request's headers to arrive
    :param body_timeout: seconds for its body to arrive after them
    :param keep_alive: seconds an idle connection stays open
    :param tls: the server's TLS context (:func:`tls_context`), or uvicorn's ``ssl_*`` settings as a dictionary
        (``ssl_certfile``, ``ssl_keyfile``, ``ssl_ca_certs``); the handshake is done by the guarded protocol
    :param http: uvicorn's HTTP implementation: ``auto`` (httptools when installed, else h11), ``httptools`` or ``h11``
    :return: the ``uvicorn.Config`` (its logging already rate-limited)
    """
    import uvicorn

    if isinstance(tls, dict) and tls:
        tls = tls_context(tls["ssl_certfile"], tls["ssl_keyfile"], tls.get("ssl_ca_certs"))
    guard = ConnectionGuard(max_connections, header_timeout, body_timeout, tls=tls or None)
    socket_class = websocket_protocol()
    websockets = {"ws": "none"}
    if socket_class is not None:  # the fast path (envs.serve.frames); without a WebSocket library, HTTP only
        websockets = {"ws": guarded_websocket(socket_class, guard), "ws_max_size": gateway.max_body,
                      "ws_per_message_deflate": False, "ws_max_queue": 4}  # fmt: skip
    config = uvicorn.Config(
        create_app(gateway), log_level="warning", access_log=False, timeout_graceful_shutdown=2,
        http=guarded_protocol(uvicorn_protocol(http), guard), limit_concurrency=max_connections + 1,
        timeout_keep_alive=keep_alive, backlog=ACCEPT_BURST, h11_max_incomplete_event_size=MAX_HEADER_BYTES,
        **websockets,
    )  # fmt: skip
    config.guard = guard
    limit_logging()  # after uvicorn's own logging set-up (in Config), which would drop the filters
    return config
