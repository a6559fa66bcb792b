"""The fast path's frames: a step and its answer as MessagePack arrays with the columns as raw little-endian bytes.

A stream's steps can travel over one WebSocket (``GET /streams/{id}/ws``) instead of one HTTP request each.
Each message is a MessagePack array (no keys, so no duplicate key can hide a second value):

- a step: ``[seq, layout, time, routes, ids, route, arc, speed, length, width, captured]``: ``routes`` a list of
  route names, ``route`` each vehicle's index into it, ``ids`` ``int64`` and the others ``float64`` columns, all
  little-endian bytes (row ``i`` is vehicle ``i``; the same units and ranges as the JSON scene), ``captured`` the
  wall-clock time of its capture [s since the Unix epoch] (required: a frame without it is refused);
- its answer: ``[200, seq, step, time, ids, accelerations, overridden, unresolved]``, the last two ``None``
  without the server's shield (``overridden``: one byte per vehicle);
- a refusal: ``[status, field, message, expected]`` (``expected``: the next ``seq`` on a 409, else ``None``).

Floats cross as their 8 bytes: exact, and no text to parse. Decoding checks the columns with a few compiled
passes and names the field of the first bad row (``vehicles[3].speed``), as the JSON path does.
Needs ``msgspec`` (the ``serve`` extra), numpy and numba (the decoder's checks), not the server's stack; the client
falls back to JSON over HTTP without msgspec.
"""

from __future__ import annotations

import time as _clock
from typing import Any

import msgspec
import numba
import numpy as np

from envs.serve.wire import LENGTH_RANGE, MAX_LAYOUT_NAME, MAX_VEHICLES, WIDTH_RANGE, WireError

_I8, _F8 = np.dtype("<i8"), np.dtype("<f8")
_COLUMNS = ("ids", "route", "arc", "speed", "length", "width")
_MAX_SEQ = 2**63 - 1


class StepFrame(msgspec.Struct, array_like=True, forbid_unknown_fields=True):
    """A step on the fast path (see the module docstring)."""

    seq: int
    layout: str
    time: float
    routes: list[str]
    ids: bytes
    route: bytes
    arc: bytes
    speed: bytes
    length: bytes
    width: bytes
    captured: float | None = None  # required; a default only so that its absence is refused by name


_DECODER = msgspec.msgpack.Decoder(StepFrame)
_ENCODER = msgspec.msgpack.Encoder()


def encode_step(seq: int, layout: str, time: float, routes: list[str] | tuple[str, ...], ids: np.ndarray,
                route: np.ndarray, arc: np.ndarray, speed: np.ndarray, length: np.ndarray,
                width: np.ndarray, captured: float | None = None) -> bytes:  # fmt: skip
    """A step frame (what the client sends).

    :param routes: the route names that ``route`` indexes
    :param captured: when the scene was captured [s since the Unix epoch] (default: now)
    :return: the MessagePack bytes
    """
    i8 = (np.ascontiguousarray(a, _I8).tobytes() for a in (ids, route))
    f8 = (np.ascontiguousarray(a, _F8).tobytes() for a in (arc, speed, length, width))
    captured = _clock.time() if captured is None else float(captured)
    return _ENCODER.encode([int(seq), layout, float(time), list(routes), *i8, *f8, captured])


class Columns(msgspec.Struct):
    """A decoded step: its sequence number, layout, time and the columns (``route``: names, per vehicle index)."""

    seq: int
    layout: str
    time: float
    routes: list[str]
    ids: np.ndarray
    route: np.ndarray
    arc: np.ndarray
    speed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    captured: float = 0.0


def decode_step(data: bytes) -> Columns:
    """Decode and check a step frame: types, sizes and the ranges of the JSON schema (compiled).

    :raises WireError: naming the field (``body``, ``seq``, ``time``, ``vehicles``, ``vehicles[i].speed``...)
    """
    try:
        frame = _DECODER.decode(data)
    except msgspec.ValidationError as error:
        raise WireError("body", f"not a step frame ({error})") from None
    except msgspec.DecodeError as error:
        raise WireError("body", f"not MessagePack ({error})") from None
    if not 1 <= frame.seq <= _MAX_SEQ:
        raise WireError("seq", f"must be from 1 to {_MAX_SEQ}, got {frame.seq}")
    if not (np.isfinite(frame.time) and 0.0 <= frame.time <= 1e9):
        raise WireError("time", f"must be a finite number of seconds from 0 to 1e9, got {frame.time}")
    if frame.captured is None:
        raise WireError("captured", "missing: a step carries the wall-clock time of its capture [s since the epoch]")
    if not (np.isfinite(frame.captured) and 0.0 <= frame.captured <= 1e11):
        raise WireError("captured", f"must be a finite number of seconds from 0 to 1e11, got {frame.captured}")
    if not 1 <= len(frame.layout) <= MAX_LAYOUT_NAME:
        raise WireError("layout", f"must be 1 to {MAX_LAYOUT_NAME} characters")
    sizes = [len(getattr(frame, name)) for name in _COLUMNS]
    n = sizes[0] // 8
    bad = next((name for name, size in zip(_COLUMNS, sizes) if size != 8 * n), None)
    if bad is not None:
        raise WireError(bad, f"{sizes[_COLUMNS.index(bad)]} bytes; every column must hold 8 bytes per vehicle "
                             f"({n} vehicles by ids)")  # fmt: skip
    if n > MAX_VEHICLES:
        raise WireError("vehicles", f"{n} vehicles, more than the schema's {MAX_VEHICLES}")
    ids, route = (np.frombuffer(getattr(frame, name), _I8) for name in ("ids", "route"))
    arc, speed, length, width = (np.frombuffer(getattr(frame, name), _F8) for name in _COLUMNS[2:])
    rule, i = _first_bad(ids, route, len(frame.routes), arc, speed, length, width, *LENGTH_RANGE, *WIDTH_RANGE)
    if rule >= 0:
        _refuse(rule, i, frame.routes, ids, route, arc, speed, length, width)
    return Columns(frame.seq, frame.layout, frame.time, frame.routes, ids, route, arc, speed, length, width,
                   frame.captured)  # fmt: skip


# The checks of a step's columns, in the order they are made (the first that fails is reported, at its first row):
# (column, kind): "index" ids >= 0 or a route index into the names sent, "finite", "range" within the bounds.
_RULES = (
    ("id", "index"), ("route", "index"), ("arc", "finite"), ("arc", "range"), ("speed", "finite"), ("speed", "range"),
    ("length", "finite"), ("length", "range"), ("width", "finite"), ("width", "range"),
)  # fmt: skip


@numba.njit(cache=True)
def _first_bad(ids, route, num_routes, arc, speed, length, width, length_low, length_high, width_low, width_high):
    """``(rule, row)``: the first of :data:`_RULES` that a column breaks and its first row breaking it; ``(-1, -1)``
    if none (one compiled pass per rule, instead of some 30 NumPy calls on every step)."""
    n = ids.shape[0]
    for i in range(n):
        if ids[i] < 0:
            return 0, i
    for i in range(n):
        if route[i] < 0 or route[i] >= num_routes:
            return 1, i
    bounds = ((arc, 0.0, np.inf), (speed, 0.0, np.inf), (length, length_low, length_high),
              (width, width_low, width_high))  # fmt: skip
    for k, (values, low, high) in enumerate(bounds):
        for i in range(n):
            if not np.isfinite(values[i]):
                return 2 + 2 * k, i
        for i in range(n):
            if values[i] < low or values[i] > high:
                return 3 + 2 * k, i
    return -1, -1


def _refuse(rule: int, i: int, routes: list[str], *columns: np.ndarray) -> None:
    """Raise the refusal of rule ``rule`` (:data:`_RULES`) broken at row ``i``.

    :raises WireError: naming ``vehicles[i].<column>``
    """
    name, kind = _RULES[rule]
    values = columns[("id", "route", "arc", "speed", "length", "width").index(name)]
    if kind == "index":
        what = "must be >= 0" if name == "id" else f"must index the {len(routes)} route names sent"
    elif kind == "finite":
        what = "must be a finite number"
    else:
        low, high = {"arc": (0.0, np.inf), "speed": (0.0, np.inf), "length": LENGTH_RANGE, "width": WIDTH_RANGE}[name]
        what = f"must be from {low} to {high}"
    raise WireError(f"vehicles[{i}].{name}", f"{what}, got {values[i]}")


def encode_reply(seq: int, step: int, time: float, ids: np.ndarray, acc: np.ndarray,
                 overridden: np.ndarray | None, unresolved: bool | None) -> bytes:  # fmt: skip
    """An answer frame (``overridden``, ``unresolved``: ``None`` without the server's shield)."""
    flags = None if overridden is None else np.ascontiguousarray(overridden, np.uint8).tobytes()
    return _ENCODER.encode([200, int(seq), int(step), float(time), np.ascontiguousarray(ids, _I8).tobytes(),
                            np.ascontiguousarray(acc, _F8).tobytes(), flags, unresolved])  # fmt: skip


def encode_error(status: int, field: str, message: str, expected: int | None = None) -> bytes:
    """A refusal frame."""
    return _ENCODER.encode([int(status), field, message, expected])


# the answer to a text message on the fast path
TEXT_REFUSAL = encode_error(415, "body", "frames must be binary MessagePack (envs.serve.frames)")


def decode_reply(data: bytes) -> dict[str, Any]:
    """An answer or refusal frame as a dictionary: ``status`` and, for 200, ``seq``, ``step``, ``time``, ``ids``,
    ``accelerations`` (arrays) and ``shield`` (``None``, or ``overridden`` and ``unresolved``); for a refusal,
    ``field``, ``error`` and ``expected``.

    :raises ValueError: not such a frame
    """
    try:
        items = msgspec.msgpack.decode(data)
    except msgspec.DecodeError as error:
        raise ValueError(f"not MessagePack ({error})") from None
    if not isinstance(items, list) or not items or not isinstance(items[0], int):
        raise ValueError("not an answer frame")
    if items[0] != 200:
        status, field, message, expected = (items + [None] * 4)[:4]
        return {"status": status, "field": str(field or ""), "error": str(message or ""), "expected": expected}
    if len(items) != 8:
        raise ValueError("not an answer frame")
    _, seq, step, time, ids, acc, flags, unresolved = items
    shield = None
    if flags is not None:
        shield = {"overridden": np.frombuffer(flags, np.uint8).astype(bool), "unresolved": bool(unresolved)}
    return {"status": 200, "seq": seq, "step": step, "time": time, "ids": np.frombuffer(ids, _I8),
            "accelerations": np.frombuffer(acc, _F8), "shield": shield}  # fmt: skip
