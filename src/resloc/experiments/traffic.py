"""Robot-to-robot traffic of a run: the bytes on the wire of each frame kind, and the
messages and bytes of every kind per trial (which fusion methods' traffic is not counted)."""

from __future__ import annotations

import numpy as np

__all__ = [
    "COUNTED_EXCHANGES",
    "WIRE_BYTES",
    "communication",
    "uncounted_traffic",
]

#: Bytes on the wire of one robot-to-robot frame of each kind (the distributed runtime's
#: version-1 schema: 36-byte header + msgpack body + 32-byte HMAC tag; a test checks them
#: against ``resloc.runtime``'s encoder). ``ack`` is one frame per sender and step plus
#: ``ack_per_link`` per acknowledged link (exact up to 3 links per frame; beyond, msgpack's
#: longer length prefix adds 1 byte per frame, not counted).
WIRE_BYTES: dict[str, int] = {
    "estimate": 173,  # x (3 f8) and P (3x3 f8)
    "ack": 80,  # header, tag and the body's keys
    "ack_per_link": 80,  # one neighbour id (i8) and one 3x3 f8 block L_i B_ij
    "consensus": 229,  # one gauge consensus exchange [M_hat, C_hat] (2x3x3 f8)
    # The sender's reading of the receiver (id i8, range and bearing 2 f8) and the keys of
    # the two optional fields, on an estimate frame when the detector uses reciprocal
    # readings (zone trust): counted once per transmission, as if each carried one reading.
    "reading": 34,
    # split CI: the sender's independent part (3x3 f8 and its key) on an estimate frame, and
    # the acknowledgement frame that tells each neighbour it was fused (ids only)
    "independent_part": 77,
    "delivery_ack": 74,
    "delivery_ack_per_link": 8,
    # factorized: the factor sigma_ji the sender keeps for the receiver (its id i8, 3x3 f8
    # and the two keys) on the estimate, per transmission as the estimates are counted (one
    # receiving link each); the pair exchange at the end of the step: the lower id's "I
    # fused you" (ids only, the delivery_ack frame above), then from the higher id one
    # frame (round 1) to its lower partners with [A, B, P_pred, sigma] (4x3x3 f8) for each
    # (exact from 1 up to 31 pairs per frame)
    "factor": 90,
    "pair_frame": 89,
    "pair_per_link": 296,
    # trigger.lambda2 = "distributed": one exchange (round, [y, s] as 4 f8, degree) per
    # directed communication link and round, framed like a CONSENSUS message (the runtime
    # does not carry it: a test builds the frame with the codec's header, msgpack and tag)
    "connectivity": 117,
    # detector.witness: each robot's notes on the neighbours it measured, one frame per robot
    # and step, each note as the runtime encodes it (docs/runtime.md: the neighbour's id i8,
    # u 2 f8, Q and j's claimed position block 2x2 f8 each, whole: 88 bytes); the frame is the
    # codec's header, msgpack {"wj": bin, "wn": bin} and tag (a test builds it): exact from 32
    # to 818 notes a frame, 1 byte over with 4-31 and 2 with 1-3 (msgpack's shorter length
    # prefixes, not subtracted). The runtime sends the notes on its estimate broadcast, so
    # the wire pays the two fields (10-14 bytes) instead of a frame of their own.
    "witness_frame": 81,
    "witness_note": 88,
}

#: End-of-step exchanges (``FusionStrategy.node_exchanges``) whose frames are counted.
COUNTED_EXCHANGES = frozenset({"acks", "consensus", "delivery_acks", "factors"})


def uncounted_traffic(fusion) -> str | None:
    """Why a fusion method's robot-to-robot traffic is not in :func:`communication`'s bytes
    (a reader must not compare it as counted), or None."""
    from resloc.cl.fusion_methods import fusion_strategy

    strategy = fusion_strategy(fusion)
    if strategy.node_refusal is not None:
        return f"centralized ({strategy.node_refusal})"
    missing = sorted(set(strategy.node_exchanges) - COUNTED_EXCHANGES)
    if missing:
        return f"its {', '.join(missing)} messages are not counted"
    return None


def communication(totals: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Robot-to-robot messages and bytes of every kind, per trial, from a run's totals.

    Parameters
    ----------
    totals : dict of str to ndarray, each shape (T,)
        ``triggered`` (estimate transmissions), ``readings`` and ``independent_parts``
        (transmissions that carry the sender's reading of the receiver / its independent
        part), ``ack_frames`` and ``ack_links`` (gauge acknowledgements),
        ``delivery_ack_frames`` and ``delivery_ack_links`` (split CI's),
        ``consensus_messages`` (gauge consensus exchanges), and factorized fusion's
        ``factors`` (transmissions carrying a factor), ``pair_ack_frames`` /
        ``pair_ack_links`` and ``pair_frames`` / ``pair_messages`` (its pair exchange), and
        ``connectivity_messages`` (the distributed ``lambda2``'s exchanges),
        ``witness_frames`` and ``witness_notes`` (the witness stage's notes).

    Returns
    -------
    dict
        ``{kind: (messages (T,), bytes (T,))}`` for ``estimate``, ``ack``, ``consensus``,
        ``pair``, ``connectivity``, ``witness`` and ``total``, at :data:`WIRE_BYTES`.
    """

    def get(key: str) -> np.ndarray:
        return np.asarray(totals.get(key, 0), np.int64)

    w = WIRE_BYTES
    est = get("triggered")
    estimate_bytes = (
        est * w["estimate"]
        + get("readings") * w["reading"]
        + get("independent_parts") * w["independent_part"]
        + get("factors") * w["factor"]
    )
    gauge_acks = get("ack_frames")
    id_acks = get("delivery_ack_frames") + get("pair_ack_frames")
    ack_bytes = (
        gauge_acks * w["ack"]
        + get("ack_links") * w["ack_per_link"]
        + id_acks * w["delivery_ack"]
        + (get("delivery_ack_links") + get("pair_ack_links")) * w["delivery_ack_per_link"]
    )
    cons, pairs = get("consensus_messages"), get("pair_frames")
    lam = get("connectivity_messages")
    out = {
        "estimate": (est, estimate_bytes),
        "ack": (gauge_acks + id_acks, ack_bytes),
        "consensus": (cons, cons * w["consensus"]),
        "pair": (pairs, pairs * w["pair_frame"] + get("pair_messages") * w["pair_per_link"]),
        "connectivity": (lam, lam * w["connectivity"]),
        "witness": (
            get("witness_frames"),
            get("witness_frames") * w["witness_frame"] + get("witness_notes") * w["witness_note"],
        ),
    }
    out["total"] = (sum(m for m, _ in out.values()), sum(b for _, b in out.values()))
    return out
