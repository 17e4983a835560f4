"""The bodies of the wire format: each message kind's fields, their types and shapes.

``FIELDS[kind]`` is the schema of one kind (version 4, ``docs/runtime.md``); arrays travel as
raw little-endian bytes whose dtype and shape the schema fixes, so a decoder never trusts a
shape from the wire. :func:`decode_body` validates everything and raises
:class:`MalformedBodyError` naming the field.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

__all__ = [
    "FIELDS",
    "FLAG_DELIVERED",
    "FLAG_DETECTED",
    "FLAG_FUSED",
    "FLAG_HEARD",
    "FLAG_REPAIRED",
    "FLAG_TRIGGERED",
    "OPTIONAL",
    "ROBOT_TO_ROBOT",
    "Kind",
    "MalformedBodyError",
    "decode_body",
    "encode_body",
    "link_flags",
]


class Kind(enum.IntEnum):
    """Message kinds. Robot-to-robot kinds (through the radio): ESTIMATE, ACK, CONSENSUS,
    REQUEST, REPLY."""

    SENSORS = 1  # world -> robot: odometry and range/bearing measurements of one step
    CHANNEL = 2  # world -> radio: this step's links and their channel outcomes
    TRUTH = 3  # world -> recorder: true poses and which measurements were attacked
    START = 4  # world -> robot: initial (or re-join) estimate
    ESTIMATE = 5  # robot -> radio -> robots: predicted estimate (x, P)
    ACK = 6  # robot -> radio -> robots: gauge acknowledgements L_i B_ij
    CONSENSUS = 7  # robot -> radio -> robots: one gauge consensus exchange
    DELIVERY = 8  # radio -> robot: robot-to-robot messages delivered to it
    REPORT = 9  # robot -> world, recorder: corrected estimate and link decisions
    STATS = 10  # radio -> recorder: messages and bytes on the wire this step
    CONTROL = 11  # anyone -> anyone: ready / join / end / stop / progress / written
    REQUEST = 12  # robot -> radio -> robots: "send me your estimate" (cached: pull protocol)
    REPLY = 13  # robot -> radio -> requesters: predicted estimate (x, P), on request


#: Kinds a robot sends to robots (what the radio model applies to).
ROBOT_TO_ROBOT = (Kind.ESTIMATE, Kind.ACK, Kind.CONSENSUS, Kind.REQUEST, Kind.REPLY)


# ---------------------------------------------------------------- schema of the bodies
@dataclass(frozen=True)
class Array:
    """An array field: dtype and shape (``-1`` for the one variable leading dimension)."""

    dtype: str
    shape: tuple[int, ...]


INT, FLOAT, BOOL, STR, BLOBS, COUNTS = "int", "float", "bool", "str", "blobs", "counts"

F8, I8, U1 = "<f8", "<i8", "|u1"

#: Fields of every kind's body. Arrays sharing a variable dimension must agree (``_ROWS``).
FIELDS: dict[Kind, dict[str, Any]] = {
    Kind.SENSORS: {
        "u": Array(F8, (2,)),
        "l2": FLOAT,
        "rs": FLOAT,
        "rc": FLOAT,
        "j": Array(I8, (-1,)),
        "z": Array(F8, (-1, 2)),
    },
    Kind.CHANNEL: {
        "i": Array(I8, (-1,)),
        "j": Array(I8, (-1,)),
        "ok": Array(U1, (-1,)),
        "fed": Array(I8, (-1,)),
    },
    Kind.TRUTH: {
        "pose": Array(F8, (-1, 3)),
        "i": Array(I8, (-1,)),
        "j": Array(I8, (-1,)),
        "att": Array(U1, (-1,)),
        "fed": Array(I8, (-1,)),
    },
    Kind.START: {
        "robot": INT,
        "x": Array(F8, (3,)),
        "P": Array(F8, (3, 3)),
        "rejoin": BOOL,
        "rt": BOOL,
    },
    Kind.ESTIMATE: {"x": Array(F8, (3,)), "P": Array(F8, (3, 3))},
    Kind.ACK: {"to": Array(I8, (-1,))},
    Kind.CONSENSUS: {"round": INT, "m": Array(F8, (2, 3, 3)), "deg": INT},
    Kind.DELIVERY: {
        "to": INT,
        "phase": INT,
        "round": INT,
        "nb": Array(I8, (-1,)),
        "msgs": BLOBS,
    },
    Kind.REPORT: {
        "robot": INT,
        "x": Array(F8, (3,)),
        "P": Array(F8, (3, 3)),
        "j": Array(I8, (-1,)),
        "flags": Array(U1, (-1,)),
        "norm": Array(F8, (-1,)),
        "rep": INT,
        "cnt": COUNTS,
    },
    Kind.STATS: {
        "robot": Array(I8, (-1,)),
        "kind": Array(I8, (-1,)),
        "msgs": Array(I8, (-1,)),
        "bytes": Array(I8, (-1,)),
        "copies": Array(I8, (-1,)),
        "jammed": Array(I8, (-1,)),
        "cnt": COUNTS,
    },
    Kind.CONTROL: {"cmd": STR, "arg": STR, "n": INT},
    Kind.REQUEST: {"round": INT, "to": Array(I8, (-1,))},
    Kind.REPLY: {
        "round": INT,
        "to": Array(I8, (-1,)),
        "x": Array(F8, (3,)),
        "P": Array(F8, (3, 3)),
    },
}

#: Optional field groups: a body carries every field of a group or none of them. An
#: ESTIMATE carries its sender's readings of this step (``rj``: the robots it measured,
#: ``rz``: range and bearing) when the team's detector uses reciprocal readings
#: (``detector.zone_trust``; the receiver takes its own row), the sender's independent
#: part ``Pi`` with split covariance intersection, and with factorized fusion the factors
#: it keeps for the robots it measured (``fj``: their ids, ``fs``: ``sigma_ji``; the
#: receiver takes its own row). With the witness stage (``detector.witness``) it carries
#: the sender's notes of the step before (``wj``: the robots it measured, ``wn``: per note
#: ``u`` (2), ``Q`` (2x2), ``P_pos`` (2x2) row-major). An ACK carries the gauge blocks
#: ``ack`` with gauge fusion; without them it is "your estimate was fused" to ``to``
#: (split CI; factorized fusion's round 0); factorized fusion's round 1 (``round``,
#: ``pair``) carries the sender's pair message ``[A, B, P_pred, sigma]`` for each (lower)
#: partner in ``to``.
OPTIONAL: dict[Kind, tuple[dict[str, Any], ...]] = {
    Kind.ESTIMATE: (
        {"rj": Array(I8, (-1,)), "rz": Array(F8, (-1, 2))},
        {"Pi": Array(F8, (3, 3))},
        {"fj": Array(I8, (-1,)), "fs": Array(F8, (-1, 3, 3))},
        {"wj": Array(I8, (-1,)), "wn": Array(F8, (-1, 10))},
    ),
    Kind.ACK: ({"ack": Array(F8, (-1, 3, 3))}, {"round": INT, "pair": Array(F8, (-1, 4, 3, 3))}),
}

#: Groups of fields whose leading dimension must be equal.
_ROWS: dict[Kind, tuple[tuple[str, ...], ...]] = {
    Kind.SENSORS: (("j", "z"),),
    Kind.ESTIMATE: (("rj", "rz"), ("fj", "fs"), ("wj", "wn")),
    Kind.CHANNEL: (("i", "j", "ok"),),
    Kind.TRUTH: (("i", "j", "att"),),
    Kind.ACK: (("to", "ack"), ("to", "pair")),
    Kind.REPORT: (("j", "flags", "norm"),),
    Kind.STATS: (("robot", "kind", "msgs", "bytes", "copies", "jammed"),),
}

#: Bits of ``REPORT.flags`` (one byte per link).
FLAG_DETECTED, FLAG_TRIGGERED, FLAG_DELIVERED, FLAG_FUSED, FLAG_HEARD = 1, 2, 4, 8, 16
#: The observer's covariance was projected back to positive definite after this link.
FLAG_REPAIRED = 32


def link_flags(outcome) -> np.ndarray:
    """``REPORT.flags`` bits of a :class:`~resloc.cl.links.LinkOutcome`, shape (E,) uint8
    (without ``FLAG_HEARD``, which the robot sets for every link it evaluated)."""
    flags = np.zeros(len(outcome.detected), dtype=np.uint8)
    for bit, arr in (
        (FLAG_DETECTED, outcome.detected),
        (FLAG_TRIGGERED, outcome.triggered),
        (FLAG_DELIVERED, outcome.delivered),
        (FLAG_FUSED, outcome.fused),
        (FLAG_REPAIRED, outcome.repaired),
    ):
        flags |= np.where(arr, bit, 0).astype(np.uint8)
    return flags


_NON_FINITE_OK = {(Kind.REPORT, "norm")}  # a discarded link's threshold norm may be nan


class MalformedBodyError(ValueError):
    """The body does not match its kind's schema (message names the field)."""


def _encode_field(spec: Any, value: Any) -> Any:
    if isinstance(spec, Array):
        a = np.ascontiguousarray(np.asarray(value).astype(spec.dtype, copy=False))
        return a.tobytes()
    if spec == INT:
        return int(value)
    if spec == FLOAT:
        return float(value)
    if spec == BOOL:
        return bool(value)
    if spec == STR:
        return str(value)
    if spec == BLOBS:
        return [bytes(b) for b in value]
    if spec == COUNTS:
        return {str(k): int(v) for k, v in value.items()}
    raise TypeError(spec)


def _decode_field(kind: Kind, name: str, spec: Any, value: Any) -> Any:
    if isinstance(spec, Array):
        if not isinstance(value, bytes):
            raise MalformedBodyError(f"{name}: not bytes")
        item = np.dtype(spec.dtype).itemsize
        fixed = math.prod(d for d in spec.shape if d != -1)
        if len(value) % (item * fixed):
            raise MalformedBodyError(f"{name}: {len(value)} bytes is not a whole number of rows")
        a = np.frombuffer(value, dtype=spec.dtype)
        shape = tuple(len(a) // fixed if d == -1 else d for d in spec.shape)
        if math.prod(shape) != len(a):
            raise MalformedBodyError(f"{name}: {len(a)} values do not fit shape {spec.shape}")
        a = a.reshape(shape).astype(spec.dtype[1:], copy=True)
        if a.dtype.kind == "f" and (kind, name) not in _NON_FINITE_OK and not np.isfinite(a).all():
            raise MalformedBodyError(f"{name}: non-finite value")
        return a
    if spec == INT:
        if not isinstance(value, int) or isinstance(value, bool):
            raise MalformedBodyError(f"{name}: not an integer")
        return value
    if spec == FLOAT:
        if not isinstance(value, float | int) or isinstance(value, bool):
            raise MalformedBodyError(f"{name}: not a number")
        if not math.isfinite(value):
            raise MalformedBodyError(f"{name}: non-finite value")
        return float(value)
    if spec == BOOL:
        if not isinstance(value, bool):
            raise MalformedBodyError(f"{name}: not a boolean")
        return value
    if spec == STR:
        if not isinstance(value, str) or len(value) > 4096:
            raise MalformedBodyError(f"{name}: not a string")
        return value
    if spec == BLOBS:
        if not isinstance(value, list) or not all(isinstance(b, bytes) for b in value):
            raise MalformedBodyError(f"{name}: not a list of byte strings")
        return value
    if spec == COUNTS:
        if not isinstance(value, dict) or not all(
            isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
            for k, v in value.items()
        ):
            raise MalformedBodyError(f"{name}: not a map of counts")
        return value
    raise TypeError(spec)


def _schema_of(kind: Kind, names: set) -> dict | None:
    """The fields a body with field ``names`` must match: ``FIELDS[kind]``, with the
    optional group when any of its fields is present (None: no schema matches)."""
    spec = FIELDS[kind]
    for group in OPTIONAL.get(kind, ()):
        if names & set(group):
            spec = {**spec, **group}
    return spec if names == set(spec) else None


def encode_body(kind: Kind, body: dict) -> bytes:
    """The msgpack bytes of ``body`` (every field of ``FIELDS[kind]``, and the optional
    group of :data:`OPTIONAL` entirely or not at all)."""
    spec = _schema_of(kind, set(body))
    if spec is None:
        raise ValueError(f"{kind.name}: fields {sorted(body)} != schema {sorted(FIELDS[kind])}")
    return msgpack.packb({k: _encode_field(spec[k], body[k]) for k in spec}, use_bin_type=True)


def decode_body(kind: Kind, raw: bytes) -> dict:
    """Decode and validate a body; raises :class:`MalformedBodyError`."""
    try:
        data = msgpack.unpackb(raw, raw=False, strict_map_key=True, max_bin_len=1 << 24)
    except Exception as exc:  # msgpack raises many types on garbage
        raise MalformedBodyError(f"undecodable body ({exc.__class__.__name__})") from None
    spec = _schema_of(kind, set(data)) if isinstance(data, dict) else None
    if spec is None:
        raise MalformedBodyError("fields do not match the schema")
    body = {k: _decode_field(kind, k, spec[k], data[k]) for k in spec}
    for group in _ROWS.get(kind, ()):
        if set(group) <= set(body) and len({len(body[k]) for k in group}) != 1:
            raise MalformedBodyError(f"{'/'.join(group)}: lengths differ")
    return body
