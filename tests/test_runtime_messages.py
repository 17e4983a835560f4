"""The runtime's wire format: round trips, authentication, replay/order/staleness, key file,
and a seeded fuzz of the decoder (random, bit-flipped, truncated and re-signed garbage)."""

from __future__ import annotations

import os
import stat
import struct
import time

import msgpack
import numpy as np
import pytest

from resloc.errors import ConfigError
from resloc.runtime import messages as m
from resloc.runtime.messages import Codec, Kind, Verifier, load_or_create_key

KEY = bytes(range(32))
CH = "resloc/team/radio/in"


def sample_bodies(rng: np.random.Generator) -> dict[Kind, dict]:
    E = int(rng.integers(0, 5))
    return {
        Kind.SENSORS: {
            "u": rng.normal(size=2),
            "l2": 1.5,
            "rs": 0.1,
            "rc": 0.0,
            "j": rng.integers(0, 9, E),
            "z": rng.normal(size=(E, 2)),
        },
        Kind.CHANNEL: {
            "i": np.arange(E),
            "j": np.arange(E)[::-1].copy(),
            "ok": np.ones(E, bool),
            "fed": np.arange(3),
        },
        Kind.TRUTH: {
            "pose": rng.normal(size=(4, 3)),
            "i": np.arange(E),
            "j": np.arange(E),
            "att": np.zeros(E, bool),
            "fed": np.arange(4),
        },
        Kind.START: {
            "robot": 2,
            "x": rng.normal(size=3),
            "P": np.eye(3),
            "rejoin": False,
            "rt": True,
        },
        Kind.ESTIMATE: {
            "x": rng.normal(size=3),
            "P": np.eye(3) * 0.01,
            "rj": rng.integers(0, 9, E),  # the optional group (zone trust's readings)
            "rz": rng.normal(size=(E, 2)),
        },
        Kind.ACK: {"to": np.arange(E), "ack": rng.normal(size=(E, 3, 3))},
        Kind.CONSENSUS: {"round": 1, "m": rng.normal(size=(2, 3, 3)), "deg": 3},
        Kind.DELIVERY: {"to": 1, "phase": 5, "round": 0, "nb": np.arange(E), "msgs": [b"a", b"bc"]},
        Kind.REPORT: {
            "robot": 1,
            "x": rng.normal(size=3),
            "P": np.eye(3),
            "j": np.arange(E),
            "flags": np.ones(E, np.uint8),
            "norm": np.full(E, np.nan),
            "rep": 0,
            "cnt": {"unheard": 2},
        },
        Kind.STATS: {
            "robot": np.arange(E),
            "kind": np.full(E, 5),
            "msgs": np.ones(E, int),
            "bytes": np.ones(E, int),
            "copies": np.ones(E, int),
            "jammed": np.zeros(E, int),
            "cnt": {},
        },
        Kind.CONTROL: {"cmd": "end", "arg": "complete", "n": 7},
        Kind.REQUEST: {"round": 2, "to": np.arange(E)},
        Kind.REPLY: {"round": 2, "to": np.arange(E), "x": rng.normal(size=3), "P": np.eye(3)},
    }


def test_every_kind_round_trips_exactly() -> None:
    rng = np.random.default_rng(0)
    codec, ver = Codec(KEY, 3), Verifier(KEY)
    for kind, body in sample_bodies(rng).items():
        frame = codec.encode(kind, 42, body, CH)
        msg = ver.open(frame, CH)
        assert msg is not None, kind
        assert (msg.kind, msg.sender, msg.step) == (kind, 3, 42)
        for name, value in body.items():
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(msg.body[name], value)
                assert msg.body[name].shape == value.shape
            else:
                assert msg.body[name] == value
    assert sum(ver.counts().values()) == 0
    assert "KEY" not in repr(codec) and KEY.hex() not in repr(codec)


def test_header_layout_is_the_documented_one() -> None:
    frame = Codec(KEY, 7).encode(Kind.ESTIMATE, 9, {"x": np.zeros(3), "P": np.eye(3)}, CH)
    magic, version, kind, sender, _, epoch, seq, ts, step = m.HEADER.unpack_from(frame)
    assert m.HEADER.size == 36 and magic == b"RL" and version == m.SCHEMA_VERSION == 5
    assert (kind, sender, seq, step) == (Kind.ESTIMATE, 7, 1, 9)
    assert abs(ts - time.time()) < 5 and epoch > 0
    assert len(frame) < 200  # compact: x, P and the header, tag


def test_unauthenticated_replayed_out_of_order_and_stale_frames_are_counted() -> None:
    codec = Codec(KEY, 1)
    body = {"x": np.zeros(3), "P": np.eye(3)}
    f1, f2, f3 = (codec.encode(Kind.ESTIMATE, k, body, CH) for k in (1, 2, 3))
    ver = Verifier(KEY, max_age_s=5.0)
    assert ver.open(Codec(bytes(32), 1).encode(Kind.ESTIMATE, 1, body, CH), CH) is None
    assert ver.open(f1, "resloc/team/robot/1/inbox") is None  # replayed onto another key
    assert ver.open(f1, CH) is not None
    assert ver.open(f3, CH) is not None
    assert ver.open(f3, CH) is None  # replay
    assert ver.open(f2, CH) is None  # older than the last accepted
    assert ver.open(f1, CH) is None  # replay of an older one
    old = codec.encode(Kind.ESTIMATE, 4, body, CH, timestamp=time.time() - 60)
    assert ver.open(old, CH) is None
    future = codec.encode(Kind.ESTIMATE, 5, body, CH, timestamp=time.time() + 60)
    assert ver.open(future, CH) is None
    c = ver.counts()
    assert c["unauthenticated"] == 2 and c["replayed"] == 2 and c["out_of_order"] == 1
    assert c["stale"] == 2 and ver.accepted == 2
    # A restarted sender (new epoch) is accepted from seq 1; the old incarnation is not.
    time.sleep(0.001)
    restarted = Codec(KEY, 1)
    assert ver.open(restarted.encode(Kind.ESTIMATE, 1, body, CH), CH) is not None
    assert ver.open(codec.encode(Kind.ESTIMATE, 6, body, CH), CH) is None


def test_schema_violations_are_malformed_even_when_signed() -> None:
    """A key holder's bug (wrong field, shape, type, non-finite value) is rejected too."""
    ver = Verifier(KEY)

    def signed(kind: int, fields: dict, seq: int) -> bytes:
        head = m.HEADER.pack(b"RL", m.SCHEMA_VERSION, kind, 2, 0, 1, seq, time.time(), 1)
        payload = head + msgpack.packb(fields, use_bin_type=True)
        return payload + m._tag(KEY, CH, payload)

    good = {"x": np.zeros(3).tobytes(), "P": np.eye(3).tobytes()}
    assert ver.open(signed(Kind.ESTIMATE, good, 1), CH) is not None
    bad_cases = [
        {"x": np.zeros(3).tobytes()},  # missing field
        good | {"extra": 1},  # extra field
        {"x": np.zeros(4).tobytes(), "P": np.eye(3).tobytes()},  # wrong shape
        {"x": "abc", "P": np.eye(3).tobytes()},  # wrong type
        {"x": np.array([np.nan, 0, 0]).tobytes(), "P": np.eye(3).tobytes()},  # non-finite
        good | {"rj": np.arange(2).tobytes()},  # half of the optional readings group
        good | {"rj": np.arange(2).tobytes(), "rz": np.ones((3, 2)).tobytes()},  # lengths
        good | {"rj": np.arange(1).tobytes(), "rz": np.array([[np.inf, 0.0]]).tobytes()},
    ]
    for seq, fields in enumerate(bad_cases, start=2):
        assert ver.open(signed(Kind.ESTIMATE, fields, seq), CH) is None
    readings = {"rj": np.arange(2).tobytes(), "rz": np.ones((2, 2)).tobytes()}
    assert ver.open(signed(Kind.ESTIMATE, good | readings, 100), CH).body["rz"].shape == (2, 2)
    ack = {"to": np.arange(2).tobytes(), "ack": np.zeros((3, 3, 3)).tobytes()}
    assert ver.open(signed(Kind.ACK, ack, 1), CH) is None  # inconsistent lengths
    assert ver.open(signed(99, good, 1), CH) is None  # unknown kind
    assert ver.counts()["malformed"] == len(bad_cases) + 2


def test_decoder_fuzz_never_raises_and_never_accepts_garbage() -> None:
    """Thousands of random, bit-flipped, truncated and extended frames (seeded)."""
    rng = np.random.default_rng(20261123)
    codec = Codec(KEY, 4)
    ver = Verifier(KEY, max_age_s=1e9, window=64)
    frames = []
    for _ in range(60):
        for kind, body in sample_bodies(rng).items():
            frames.append(codec.encode(kind, 1, body, CH))
    accepted_before = 0
    tried = 0
    for frame in frames:
        for mode in range(8):
            data = bytearray(frame)
            if mode == 0:  # random bytes of a random length
                data = bytearray(rng.bytes(int(rng.integers(0, 300))))
            elif mode == 1:  # one bit flipped anywhere
                pos = int(rng.integers(0, len(data)))
                data[pos] ^= 1 << int(rng.integers(0, 8))
            elif mode == 2:  # truncated
                data = data[: int(rng.integers(0, len(data)))]
            elif mode == 3:  # extended
                data += rng.bytes(int(rng.integers(1, 20)))
            elif mode == 4:  # several bytes overwritten
                for _ in range(int(rng.integers(2, 10))):
                    data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
            elif mode == 5:  # valid header, random body, correct tag: the schema must hold
                body = rng.bytes(int(rng.integers(0, 120)))
                payload = bytes(data[: m.HEADER.size]) + body
                data = bytearray(payload + m._tag(KEY, CH, payload))
            elif mode == 6:  # random msgpack structure, correctly signed
                obj = {
                    str(rng.integers(0, 3)): rng.bytes(int(rng.integers(0, 50))),
                    "x": [1, 2.5, None],
                    "P": {"a": 1},
                }
                payload = bytes(data[: m.HEADER.size]) + msgpack.packb(obj, use_bin_type=True)
                data = bytearray(payload + m._tag(KEY, CH, payload))
            else:  # header fields scrambled (kind, version, magic)
                struct.pack_into("<B", data, int(rng.integers(0, 4)), int(rng.integers(0, 256)))
            tried += 1
            msg = ver.open(bytes(data), CH)  # must never raise
            if msg is not None and bytes(data) != frame:  # a no-op mutation is the frame
                accepted_before += 1
    assert tried >= 4000
    # Only mode 5/6 can carry a valid tag; they must fail the schema; a flipped bit or a
    # truncation never authenticates.
    assert accepted_before == 0
    c = ver.counts()
    assert c["unauthenticated"] > 1000 and c["malformed"] > 500 and c["truncated"] > 100
    assert sum(c.values()) + ver.accepted == tried and ver.accepted <= 5  # no-op mutations


def test_key_file_created_0600_and_checked(tmp_path) -> None:
    path = tmp_path / "team.key"
    key = load_or_create_key(path)
    assert len(key) == 32 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert load_or_create_key(path) == key
    os.chmod(path, 0o644)
    with pytest.raises(ConfigError, match="chmod 600") as info:
        load_or_create_key(path)
    assert key.hex() not in str(info.value)
    os.chmod(path, 0o600)
    path.write_text("not hex\n")
    with pytest.raises(ConfigError, match="not a key"):
        load_or_create_key(path)
