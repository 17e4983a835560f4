"""The wire format of the distributed runtime: a versioned, authenticated binary schema.

Every message on the wire, robot-to-robot or infrastructure, is one frame::

    header (36 bytes, little-endian struct ``HEADER``)
        magic      2s   b"RL"
        version    u8   SCHEMA_VERSION (5)
        kind       u8   a :class:`Kind`
        sender     u16  robot id 0..65519, or one of the process ids (WORLD, RADIO, ...)
        reserved   u16  0
        epoch      u64  the sender process's incarnation (ns since the epoch at its start)
        seq        u64  per (sender, kind) sequence number, from 1
        timestamp  f64  sender's wall clock (s since the Unix epoch) when it was sent
        step       u32  simulation step the message belongs to
    body         msgpack map of the kind's fields (``FIELDS``); arrays are raw little-endian
                 bytes whose shapes the schema fixes
    tag (32 bytes) HMAC-SHA256 with the team key over
                 ``len(channel) (u16) + channel + header + body``

The *channel* is the Zenoh key expression the frame is published on (robot-to-robot frames:
the radio's input key, which they keep when the radio forwards them). Binding it into the
tag means a frame replayed onto another key expression fails authentication. Sequence
numbers count per (sender, kind, channel).

A receiver (:class:`Verifier`) checks, in this order: length, magic, version, tag (before
parsing anything else), freshness (``|now - timestamp| <= max_age_s``), sequence (a replayed
``(epoch, seq)`` or an older epoch is ``replayed``; a sequence number below the last accepted
one of the same incarnation is ``out_of_order``), then the body against the kind's schema
(``malformed``: unknown kind, undecodable msgpack, missing or extra field, wrong type, wrong
shape, non-finite float, inconsistent lengths). A rejected message is counted by reason and
dropped: it never raises out of :meth:`Verifier.open` and never reaches a filter.
"""

from __future__ import annotations

import collections
import enum
import hashlib
import hmac
import math
import os
import secrets
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

from resloc.errors import ConfigError
from resloc.runtime.schema import (
    FIELDS,
    FLAG_DELIVERED,
    FLAG_DETECTED,
    FLAG_FUSED,
    FLAG_HEARD,
    FLAG_REPAIRED,
    FLAG_TRIGGERED,
    ROBOT_TO_ROBOT,
    Kind,
    MalformedBodyError,
    decode_body,
    encode_body,
)

__all__ = [
    "FIELDS",
    "FLAG_DELIVERED",
    "FLAG_DETECTED",
    "FLAG_FUSED",
    "FLAG_HEARD",
    "FLAG_REPAIRED",
    "FLAG_TRIGGERED",
    "HEADER",
    "MAX_ROBOT_ID",
    "RADIO",
    "RECORDER",
    "ROBOT_TO_ROBOT",
    "SCHEMA_VERSION",
    "SUPERVISOR",
    "TAG_SIZE",
    "WORLD",
    "Codec",
    "Kind",
    "Message",
    "RejectReason",
    "Verifier",
    "decode_body",
    "encode_body",
    "load_or_create_key",
]

SCHEMA_VERSION = 5
MAGIC = b"RL"
HEADER = struct.Struct("<2sBBHHQQdI")
TAG_SIZE = 32
KEY_BYTES = 32

#: Sender ids of the infrastructure processes (robots use 0 .. MAX_ROBOT_ID).
WORLD, RADIO, RECORDER, SUPERVISOR = 0xFFF0, 0xFFF1, 0xFFF2, 0xFFF3
MAX_ROBOT_ID = 0xFFEF


class RejectReason(enum.StrEnum):
    """Why a frame was dropped (counted per reason)."""

    TRUNCATED = "truncated"
    BAD_MAGIC = "bad_magic"
    BAD_VERSION = "bad_version"
    UNAUTHENTICATED = "unauthenticated"
    STALE = "stale"
    REPLAYED = "replayed"
    OUT_OF_ORDER = "out_of_order"
    MALFORMED = "malformed"


# ---------------------------------------------------------------- frames
@dataclass(frozen=True)
class Message:
    """One verified message. ``raw`` is the frame as received (the radio forwards it)."""

    kind: Kind
    sender: int
    epoch: int
    seq: int
    timestamp: float
    step: int
    body: dict
    raw: bytes = field(repr=False)


def load_or_create_key(path: str | Path) -> bytes:
    """The team key from ``path`` (64 hex characters); created with mode 0600 if absent.

    Raises
    ------
    ConfigError
        Unreadable, malformed, or readable by group/others (the key is never printed).
    """
    p = Path(path)
    if not p.exists():
        # Written to a private temporary file, then linked into place: a process that
        # starts at the same time sees no key or the whole key, never half of it.
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w", encoding="ascii") as fh:
                fh.write(secrets.token_hex(KEY_BYTES) + "\n")
            try:
                os.link(tmp, p)
            except FileExistsError:
                pass  # another process created it first: use theirs
            finally:
                tmp.unlink()
        except OSError as exc:
            raise ConfigError(
                f"--key-file {p}: cannot create ({exc.strerror}); choose a writable path"
            ) from None
    try:
        mode = p.stat().st_mode & 0o777
        text = p.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(
            f"--key-file {p}: cannot read ({exc.__class__.__name__}); check the path"
        ) from None
    if mode & 0o077:
        raise ConfigError(
            f"--key-file {p}: readable by group or others (mode {mode:04o}); run chmod 600 {p}"
        )
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise ConfigError(
            f"--key-file {p}: not a key (expected {2 * KEY_BYTES} hex characters); "
            "delete it to have a new one created"
        )
    return key


class Codec:
    """Builds authenticated frames for one sender (one process incarnation)."""

    def __init__(self, key: bytes, sender: int) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError("team key must be 32 bytes")
        self._key = key
        self.sender = int(sender)
        self.epoch = time.time_ns()
        self._seq: dict[tuple[Kind, int, str], int] = collections.defaultdict(int)

    def __repr__(self) -> str:  # never show the key
        return f"Codec(sender={self.sender})"

    def encode(
        self,
        kind: Kind,
        step: int,
        body: dict,
        channel: str,
        sender: int | None = None,
        timestamp: float | None = None,
    ) -> bytes:
        """One frame of ``kind`` for ``step`` on ``channel`` (its key expression);
        ``sender`` overrides this codec's sender for a process that hosts several robots."""
        who = self.sender if sender is None else int(sender)
        self._seq[(kind, who, channel)] += 1
        head = HEADER.pack(
            MAGIC,
            SCHEMA_VERSION,
            int(kind),
            who,
            0,
            self.epoch,
            self._seq[(kind, who, channel)],
            time.time() if timestamp is None else float(timestamp),
            int(step),
        )
        payload = head + encode_body(kind, body)
        return payload + _tag(self._key, channel, payload)


def _tag(key: bytes, channel: str, payload: bytes) -> bytes:
    ch = channel.encode("utf-8")
    return hmac.new(key, struct.pack("<H", len(ch)) + ch + payload, hashlib.sha256).digest()


@dataclass
class _Stream:
    epoch: int
    last: int
    recent: collections.deque
    seen: set


class Verifier:
    """Checks incoming frames and counts what it rejects (:class:`RejectReason`).

    Parameters
    ----------
    key : bytes
        The team key.
    max_age_s : float
        Frames whose timestamp differs from the local clock by more than this are stale.
    window : int
        How many recent sequence numbers per (sender, kind) are remembered to tell a replay
        from a reordering.
    """

    def __init__(self, key: bytes, max_age_s: float = 10.0, window: int = 1024) -> None:
        self._key = key
        self.max_age_s = float(max_age_s)
        self.window = int(window)
        self.rejected: collections.Counter = collections.Counter()
        self.accepted = 0
        self._streams: dict[tuple[int, int, str], _Stream] = {}

    def __repr__(self) -> str:
        return f"Verifier(accepted={self.accepted}, rejected={dict(self.rejected)})"

    def _reject(self, reason: RejectReason) -> None:
        self.rejected[reason.value] += 1

    def open(self, frame: bytes, channel: str, now: float | None = None) -> Message | None:
        """The verified message in ``frame`` received on ``channel``, or None (rejected and
        counted). Never raises."""
        try:
            return self._open(bytes(frame), channel, time.time() if now is None else now)
        except Exception:  # defensive: a decoder bug must not crash a robot
            self._reject(RejectReason.MALFORMED)
            return None

    def _open(self, frame: bytes, channel: str, now: float) -> Message | None:
        if len(frame) < HEADER.size + TAG_SIZE:
            self._reject(RejectReason.TRUNCATED)
            return None
        magic, version, kind, sender, _, epoch, seq, ts, step = HEADER.unpack_from(frame)
        if magic != MAGIC:
            self._reject(RejectReason.BAD_MAGIC)
            return None
        if version != SCHEMA_VERSION:
            self._reject(RejectReason.BAD_VERSION)
            return None
        payload, tag = frame[:-TAG_SIZE], frame[-TAG_SIZE:]
        if not hmac.compare_digest(_tag(self._key, channel, payload), tag):
            self._reject(RejectReason.UNAUTHENTICATED)
            return None
        if not math.isfinite(ts) or abs(now - ts) > self.max_age_s:
            self._reject(RejectReason.STALE)
            return None
        try:
            kind = Kind(kind)
        except ValueError:
            self._reject(RejectReason.MALFORMED)
            return None
        stream = self._streams.get((sender, kind, channel))
        if stream is not None:
            if epoch < stream.epoch or (epoch == stream.epoch and seq in stream.seen):
                self._reject(RejectReason.REPLAYED)
                return None
            if epoch == stream.epoch and seq < stream.last:
                self._reject(RejectReason.OUT_OF_ORDER)
                return None
        try:
            body = decode_body(kind, payload[HEADER.size :])
        except MalformedBodyError:
            self._reject(RejectReason.MALFORMED)
            return None
        if stream is None or epoch > stream.epoch:  # first contact or a restarted sender
            stream = _Stream(epoch, 0, collections.deque(), set())
            self._streams[(sender, kind, channel)] = stream
        stream.last = seq
        stream.recent.append(seq)
        stream.seen.add(seq)
        if len(stream.recent) > self.window:
            stream.seen.discard(stream.recent.popleft())
        self.accepted += 1
        return Message(kind, sender, epoch, seq, ts, step, body, frame)

    def counts(self) -> dict[str, int]:
        """Rejections so far by reason (every reason present, zeros included)."""
        return {r.value: int(self.rejected.get(r.value, 0)) for r in RejectReason}
