"""The planner server: one planning stream per intersection and client, scenes in, accelerations out.

Built with FastAPI (pydantic models, OpenAPI schema at ``/openapi.json`` and ``/docs``); run by
``sb3-graph serve`` (:mod:`envs.commands.serve`) under uvicorn. Endpoints:

- ``GET /health``: liveness; ``GET /version``: what the server runs (:class:`~envs.serve.schema.ServerInfo`);
- ``POST /streams``: open a stream (its own planner state: AIM's reservations, the shield's plans,
  signal phases), ``201`` with its id;
- ``POST /streams/{id}/step``: a scene (:class:`~envs.serve.schema.SceneIn`), answered with one
  acceleration per vehicle; ``POST /streams/{id}/reset``: a new episode; ``DELETE /streams/{id}``: close.

Bad input gets a 4xx whose body names the field (:class:`~envs.serve.schema.ErrorReply`), and the
stream and the server go on: 401 a missing or wrong token, 404 an unknown stream, 413 a body over
the limit, 422 a malformed scene (wrong type, unknown field, NaN or infinity, out of range, unknown
route, duplicate id, time going back, another layout, too many vehicles), 429 too many streams.
Every answer carries ``Server-Timing: app;dur=<ms>``, the server's own time for it.

The endpoints are ``async`` and plan on the event loop: one decision at a time, no thread hand-off
(a planner is CPU work; on one core, threads would only add switching).
"""

from __future__ import annotations

import copy
import hmac
import json
import math
import secrets
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError

from envs.planners.base import Planner
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

# Paths anyone may read without the token (liveness and the schema).
OPEN_PATHS = frozenset({"/health", "/openapi.json", "/docs", "/docs/oauth2-redirect"})
ERRORS = {code: {"model": ErrorReply} for code in (401, 404, 413, 422, 429)}


class RequestError(Exception):
    """A refused request: its status, the field and the message (the body of :class:`ErrorReply`)."""

    def __init__(self, status: int, field: str, message: str) -> None:
        super().__init__(message)
        self.status, self.field, self.message = status, field, message


@dataclass
class Stream:
    """One planning stream: its planner (its own state) and its clock."""

    id: str
    layout: str
    planner: Planner
    steps: int = 0
    last_time: float = -math.inf
    last_used: float = field(default_factory=time.monotonic)


def _error(status: int, field_name: str, message: str) -> JSONResponse:
    return JSONResponse({"error": f"{field_name}: {message}", "field": field_name}, status_code=status)


def _field_of(loc: tuple) -> str:
    """``("body", "vehicles", 3, "speed")`` -> ``"vehicles[3].speed"``."""
    parts = list(loc[1:] if loc and loc[0] == "body" else loc)
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "body"


def _shared_parts(planner: Any, depth: int = 0) -> list[Any]:
    """Parts of a planner that every stream may share: stateless learned planners (their models)."""
    from envs.planners.gnn import GNNPlanner

    if isinstance(planner, GNNPlanner):  # keeps no state between scenes (see GNNPlanner.act_many)
        return [planner]
    inner = getattr(planner, "planner", None)
    return _shared_parts(inner, depth + 1) if isinstance(inner, Planner) and depth < 8 else []


class PlannerService:
    """The server's state: the planner prototype, the scene builder and the open streams.

    :param spec: planner spec (as ``evaluate --planner``; not a remote one)
    :param env_id: gymnasium id whose configuration (layout, policy period, limits) the server uses
    :param env_kwargs: ``gym.make`` keyword arguments of that environment
    :param shield: wrap the planner in the safety shield (per stream)
    :param token: if given, every request but :data:`OPEN_PATHS` must carry ``Authorization: Bearer <token>``
    :param max_streams: most streams open at once
    :param stream_timeout: a stream unused for this long [s] is closed when a new one opens
    :param max_body: largest request body [bytes]
    """

    def __init__(
        self,
        spec: str,
        env_id: str,
        env_kwargs: dict[str, Any] | None = None,
        shield: bool = False,
        token: str | None = None,
        max_streams: int = 1000,
        stream_timeout: float = 600.0,
        max_body: int = 1 << 20,
    ) -> None:
        from envs.evaluation.harness import env_config
        from envs.planners import SHIELD_SUFFIX, check_planner_spec, make_planner

        key = check_planner_spec(spec)
        if shield and not key.endswith(SHIELD_SUFFIX):
            key += SHIELD_SUFFIX
        self.spec, self.env_id, self.shield = key, env_id, key.endswith(SHIELD_SUFFIX)
        config = env_config(env_id, env_kwargs)
        self.builder = SceneBuilder(config)
        self.prototype = make_planner(key)
        check = getattr(self.prototype, "check_capacity", None)
        if check is not None:
            check(int(config["max_vehicles"]), key)
        self._memo_seed = {id(part): part for part in _shared_parts(self.prototype)}
        self._memo_seed[id(self.builder.layout)] = self.builder.layout
        self.token = token.encode() if token else None
        self.max_streams, self.stream_timeout, self.max_body = int(max_streams), float(stream_timeout), int(max_body)
        self.streams: dict[str, Stream] = {}
        self.warm_up()

    def new_planner(self) -> Planner:
        """A planner with its own state (a copy of the unused prototype; learned models are shared)."""
        return copy.deepcopy(self.prototype, dict(self._memo_seed))

    def warm_up(self) -> None:
        """One decision on a small scene, so that the first stream does not pay for compiling kernels."""
        lay = self.builder.layout
        cars = [SimpleNamespace(id=i, route=lay.route_names[i], arc=10.0, speed=5.0, length=5.0, width=2.0)
                for i in range(min(2, lay.num_routes))]  # fmt: skip
        planner = self.new_planner()
        planner.reset(0)
        planner.act(self.builder.scene(lay.name, 0.0, cars))

    def info(self) -> dict[str, Any]:
        from envs.planners import planner_name
        from sb3_graph import __version__

        cfg = self.builder.config
        return ServerInfo(
            package=__version__, schema_version=SCHEMA_VERSION, planner=planner_name(self.spec), spec=self.spec,
            shield=self.shield, env=self.env_id, layout=self.builder.layout.name, dt=self.builder.dt,
            a_min=-float(cfg["max_acceleration"]), a_max=float(cfg["max_acceleration"]),
            max_vehicles=self.builder.limits.max_vehicles, max_speed=self.builder.limits.max_speed,
            max_streams=self.max_streams,
        ).model_dump()  # fmt: skip

    def authorized(self, header: bytes | None) -> bool:
        if self.token is None:
            return True
        return header is not None and hmac.compare_digest(header, b"Bearer " + self.token)

    def open(self, request: OpenRequest) -> Stream:
        if request.layout != self.builder.layout.name:
            raise RequestError(422, "layout", f"this server plans for layout {self.builder.layout.name!r}, "
                                              f"got {request.layout!r}")  # fmt: skip
        if request.dt is not None and abs(request.dt - self.builder.dt) > 1e-9:
            raise RequestError(422, "dt", f"this server's policy period is {self.builder.dt} s, got {request.dt}")
        self.expire()
        if len(self.streams) >= self.max_streams:
            raise RequestError(429, "streams", f"{len(self.streams)} streams are open, the most this server takes; "
                                               "close one first")  # fmt: skip
        planner = self.new_planner()
        planner.reset(request.seed)
        stream = Stream(secrets.token_hex(8), request.layout, planner)
        self.streams[stream.id] = stream
        return stream

    def expire(self) -> None:
        """Close the streams unused for longer than ``stream_timeout``."""
        now = time.monotonic()
        for sid in [s.id for s in self.streams.values() if now - s.last_used > self.stream_timeout]:
            del self.streams[sid]

    def stream(self, sid: str) -> Stream:
        stream = self.streams.get(sid)
        if stream is None:
            raise RequestError(404, "stream", f"no open stream {sid[:40]!r} (closed, expired, or never opened)")
        stream.last_used = time.monotonic()
        return stream

    def step(self, sid: str, scene_in: SceneIn) -> dict[str, Any]:
        stream = self.stream(sid)
        if scene_in.time < stream.last_time:
            raise RequestError(422, "time", f"{scene_in.time} s is before the stream's last scene "
                                            f"({stream.last_time} s); reset the stream for a new episode")  # fmt: skip
        try:
            scene = self.builder.scene(scene_in.layout, scene_in.time, scene_in.vehicles)
        except WireError as error:
            raise RequestError(422, error.field, error.message) from None
        planner = stream.planner
        unresolved = getattr(planner, "unresolved", 0)
        acc = np.asarray(planner.act(scene), dtype=float).reshape(-1)
        if acc.shape[0] != scene.num_vehicles or not np.isfinite(acc).all():
            raise RuntimeError(f"the planner answered {acc.shape[0]} accelerations (finite: "
                               f"{bool(np.isfinite(acc).all())}) for {scene.num_vehicles} vehicles")  # fmt: skip
        stream.steps += 1
        stream.last_time = scene_in.time
        reply = {"stream": sid, "step": stream.steps, "time": scene_in.time, "ids": scene.vehicle_id.tolist(),
                 "accelerations": acc.tolist(), "shield": None}  # fmt: skip
        if self.shield:  # what the server's shield did, for the client's counters (the harness reports them)
            reply["shield"] = {"overridden": planner.last_overridden.tolist(),
                               "unresolved": planner.unresolved > unresolved}  # fmt: skip
        return reply

    def reset(self, sid: str, request: ResetRequest) -> Stream:
        stream = self.stream(sid)
        stream.planner.reset(request.seed)
        stream.steps, stream.last_time = 0, -math.inf
        return stream

    def close(self, sid: str) -> None:
        self.stream(sid)
        del self.streams[sid]


def _stream_reply(service: PlannerService, stream: Stream) -> dict[str, Any]:
    return {"stream": stream.id, "layout": stream.layout, "dt": service.builder.dt, "steps": stream.steps}


class _Guard:
    """ASGI middleware: the token check and the body limit, before any parsing.

    :param app: the application
    :param service: the server's state (its token and body limit)
    """

    def __init__(self, app, service: PlannerService) -> None:
        self.app, self.service = app, service

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope["headers"])
        if scope["path"] not in OPEN_PATHS and not self.service.authorized(headers.get(b"authorization")):
            return await _error(401, "authorization", "missing or wrong token (send 'Authorization: Bearer <token>')")(
                scope, receive, send
            )
        limit = self.service.max_body
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


def create_app(service: PlannerService) -> FastAPI:
    """The FastAPI application around a :class:`PlannerService`.

    :param service: the server's state
    :return: the ASGI application (uvicorn runs it)
    """
    app = FastAPI(
        title="sb3-graph planner server",
        version=str(SCHEMA_VERSION),
        description="Scenes of a cooperative intersection in, one acceleration per vehicle out (see docs/serve.md).",
    )
    app.state.service = service

    @app.exception_handler(RequestError)
    async def _refused(request: Request, error: RequestError) -> JSONResponse:
        return _error(error.status, error.field, error.message)

    @app.exception_handler(RequestValidationError)
    async def _malformed(request: Request, error: RequestValidationError) -> JSONResponse:
        first = error.errors()[0]
        name = _field_of(tuple(first.get("loc", ())))
        if first.get("type") == "json_invalid":
            name = "body"
        return _error(422, name, str(first.get("msg", "invalid")))

    @app.get("/health", response_model=Health)
    async def health() -> dict[str, Any]:
        return {"status": "ok", "streams": len(service.streams)}

    @app.get("/version", response_model=ServerInfo, responses=ERRORS)
    async def version() -> dict[str, Any]:
        return service.info()

    @app.post("/streams", response_model=StreamReply, status_code=201, responses=ERRORS)
    async def open_stream(request: OpenRequest) -> JSONResponse:
        return JSONResponse(_stream_reply(service, service.open(request)), status_code=201)

    scene_schema = {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/SceneIn"}}},
                    "required": True}  # fmt: skip

    @app.post("/streams/{stream}/step", response_model=StepReply, responses=ERRORS,
              openapi_extra={"requestBody": scene_schema})  # fmt: skip
    async def step(stream: str, request: Request) -> Response:
        # The hot path parses the raw body with pydantic's own JSON parser (about half the time of
        # json.loads plus validation); the schema is SceneIn's all the same (documented above).
        try:
            scene = SceneIn.model_validate_json(await request.body())
        except ValidationError as error:
            first = error.errors()[0]
            name = "body" if first.get("type") == "json_invalid" else _field_of(tuple(first.get("loc", ())))
            raise RequestError(422, name, str(first.get("msg", "invalid"))) from None
        # json.dumps writes each float so that it reads back exactly (the identity with in-process runs)
        return Response(json.dumps(service.step(stream, scene)), media_type="application/json")

    @app.post("/streams/{stream}/reset", response_model=StreamReply, responses=ERRORS)
    async def reset(stream: str, request: ResetRequest) -> dict[str, Any]:
        return _stream_reply(service, service.reset(stream, request))

    @app.delete("/streams/{stream}", status_code=204, responses=ERRORS)
    async def close(stream: str) -> Response:
        service.close(stream)
        return Response(status_code=204)

    base_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        """FastAPI's schema, plus the models of the step's body (parsed in the endpoint, not by FastAPI)."""
        if app.openapi_schema is None:
            schema = base_openapi()
            scene = SceneIn.model_json_schema(ref_template="#/components/schemas/{model}")
            schema.setdefault("components", {}).setdefault("schemas", {}).update(scene.pop("$defs", {}))
            schema["components"]["schemas"]["SceneIn"] = scene
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi
    app.add_middleware(_Guard, service=service)
    return app
