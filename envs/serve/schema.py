"""The pydantic models of the planner server's requests and replies (its OpenAPI schema).

Units are physical (SI): metres, seconds, metres per second, metres per second squared. Every model
forbids unknown fields and non-finite numbers, and takes numbers strictly (``"5"`` is not a number,
``5.0`` is not an id), so a mistake is refused with the field's name instead of guessed at.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from envs.serve.wire import LENGTH_RANGE, MAX_LAYOUT_NAME, MAX_VEHICLES, WIDTH_RANGE

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class Vehicle(BaseModel):
    """One vehicle of the scene."""

    model_config = _STRICT

    id: int = Field(ge=0, le=2**63 - 1, description="unique in the scene; stable while the vehicle is in it")
    route: str = Field(min_length=1, max_length=64, description="route name, e.g. 'south->north'")
    arc: float = Field(ge=0.0, description="centre position along the route from its start [m]")
    speed: float = Field(ge=0.0, description="speed [m/s]")
    length: float = Field(ge=LENGTH_RANGE[0], le=LENGTH_RANGE[1], description="vehicle length [m]")
    width: float = Field(ge=WIDTH_RANGE[0], le=WIDTH_RANGE[1], description="vehicle width [m]")


class SceneIn(BaseModel):
    """Every vehicle at one instant: the planner answers one acceleration for each."""

    model_config = _STRICT

    layout: str = Field(min_length=1, max_length=MAX_LAYOUT_NAME, description="intersection layout name: '4way', "
                        "'3way', 'inD' or 'net:FILE' (the server's own layout)")  # fmt: skip
    time: float = Field(ge=0.0, le=1e9, description="simulated time [s]; never decreases within a stream")
    captured: float = Field(ge=0.0, le=1e11, description="when the scene was captured, on the wall clock [s since the "
                            "Unix epoch, UTC]: a scene from the future (beyond the server's clock plus a small skew) "
                            "is refused, and so is one older than the server's max_scene_age")  # fmt: skip
    vehicles: list[Vehicle] = Field(max_length=MAX_VEHICLES, description="row i of the answer is vehicles[i]")
    seq: int = Field(ge=1, le=2**63 - 1, description="the step's sequence number in the stream: 1 after an open or "
                     "a reset, then one more per step; the same number again returns the cached answer (a retry), "
                     "any other is refused (409)")


class ShieldReport(BaseModel):
    """What the server's shield (``--shield``) did in one step."""

    overridden: list[bool] = Field(description="per vehicle, in the order of the scene: the shield replaced the "
                                   "planner's command")  # fmt: skip
    unresolved: bool = Field(description="no safe plan was found: every vehicle brakes")


class SearchReport(BaseModel):
    """The searches of the stream's ``lookahead`` beside the steps, since the stream opened or was reset."""

    started: float = Field(description="searches started")
    applied: float = Field(description="searches whose windows were applied")
    late: float = Field(description="searches that answered after the step they were searched for")
    dropped: float = Field(description="searches not applied: a horizon late or more, or their process lost")
    mismatched: float = Field(description="answers for a scene no longer the stream's (a reset, another layout)")
    expired: float = Field(default=0.0, description="times the windows in force grew older than the search's "
                           "horizon and gave way to glide's own")  # fmt: skip
    worker_restarts: float = Field(description="search processes replaced after they ended")
    age_s: float = Field(description="mean age of the windows in force [s of scene time]")
    age_s_max: float = Field(description="largest age of the windows in force [s]")
    ahead_s: float = Field(description="how far ahead the searches were predicted, on average [s]")


class StepReply(BaseModel):
    """The planner's answer to one scene."""

    stream: str = Field(description="the stream")
    seq: int = Field(description="the request's sequence number")
    step: int = Field(description="steps answered in this stream since it was opened or reset (this one included)")
    time: float = Field(description="the scene's time [s]")
    ids: list[int] = Field(description="the vehicles' ids, in the order of the scene")
    accelerations: list[float] = Field(description="commanded longitudinal acceleration of each vehicle [m/s^2]")
    shield: ShieldReport | None = Field(default=None, description="the server's shield; null without --shield")
    search: SearchReport | None = Field(default=None, description="the searches of a lookahead planner beside the "
                                        "steps (absent for other planners)")  # fmt: skip


class OpenRequest(BaseModel):
    """Open a planning stream: one intersection, one client, its own planner state."""

    model_config = _STRICT

    layout: str = Field(min_length=1, max_length=MAX_LAYOUT_NAME, description="the intersection the stream's scenes "
                        "are of")  # fmt: skip
    dt: float | None = Field(default=None, gt=0.0, le=10.0, description="policy period the client steps at [s]; "
                             "must be the server's (checked when given)")
    seed: int | None = Field(default=None, ge=0, le=2**32 - 1, description="seed of the planner's randomness")


class ResetRequest(BaseModel):
    """Start a new episode in a stream: the planner forgets its state (reservations, signal phases...)."""

    model_config = _STRICT

    seed: int | None = Field(default=None, ge=0, le=2**32 - 1, description="seed of the planner's randomness")


class StreamReply(BaseModel):
    """A stream's identity and settings."""

    stream: str = Field(description="id of the stream, used in its URLs")
    layout: str = Field(description="its layout")
    dt: float = Field(description="policy period [s]")
    steps: int = Field(description="steps answered since it was opened or reset")


class ServerInfo(BaseModel):
    """What the server runs."""

    package: str = Field(description="sb3-graph version")
    schema_version: int = Field(description="version of the wire schema")
    planner: str = Field(description="the planner's report name")
    spec: str = Field(description="the planner spec it was started with")
    shield: bool = Field(description="whether the server shields the planner")
    env: str = Field(description="gymnasium id of the environment whose settings the server uses")
    layout: str = Field(description="the intersection layout")
    dt: float = Field(description="policy period [s]")
    a_min: float = Field(description="smallest acceleration [m/s^2]")
    a_max: float = Field(description="largest acceleration [m/s^2]")
    max_vehicles: int = Field(description="most vehicles in one scene")
    max_speed: float = Field(description="speed cap [m/s]")
    max_scene_age: float | None = Field(default=None, description="a scene captured longer ago than this is refused "
                                        "(its shield's declared latency bound) [s]; null: not checked")  # fmt: skip
    max_streams: int = Field(description="most streams open at once")
    max_streams_per_client: int = Field(description="most streams one client (token, or address without a "
                                        "token) may hold open")
    workers: int = Field(description="planning processes (0: planned on the server's event loop)")
    routes: dict[str, float] = Field(description="the layout's routes: name (what a scene's vehicle sends as "
                                     "'route') -> length [m] (its 'arc' runs from 0 to it)")


class SearchTotals(BaseModel):
    """The searches of a ``lookahead`` beside the steps, summed over every stream since the server started."""

    started: float = Field(description="searches started")
    applied: float = Field(description="searches whose windows were applied")
    late: float = Field(description="searches that answered after the step they were searched for")
    dropped: float = Field(description="searches not applied: a horizon late or more, or their process lost")
    mismatched: float = Field(description="answers for a scene that was no longer the stream's (a reset)")
    expired: float = Field(description="times windows in force grew older than the horizon")
    worker_restarts: float = Field(description="search processes replaced after they ended")
    age_s: float = Field(description="mean age of the windows in force [s of scene time], weighted by searches")
    age_s_max: float = Field(description="largest age of the windows in force [s of scene time]")


class Health(BaseModel):
    """Liveness."""

    status: str = Field(description="'ok'")
    streams: int = Field(description="streams open now")
    workers: int = Field(description="planning processes running now (0: planning in the server's process)")
    restarts: int = Field(description="planning processes replaced since the start (ended, or killed over the "
                                      "time limit)")
    lost_streams: int = Field(description="streams lost with their planning process since the start")
    searches: SearchTotals | None = Field(default=None, description="the searches of a lookahead planner beside the "
                                          "steps, over every stream since the start (null for another planner)")


class ErrorReply(BaseModel):
    """A refused request (4xx)."""

    error: str = Field(description="one line: the field and what is wrong with it")
    field: str = Field(description="the offending field, e.g. 'vehicles[3].speed', 'stream', 'seq', 'authorization', "
                       "'host', 'content-type', 'body', 'path', 'method'")
    expected: int | None = Field(default=None, description="409 on 'seq': the sequence number a new step must carry")
