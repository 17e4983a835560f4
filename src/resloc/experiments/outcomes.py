"""Per-trial counts of one estimator's link outcomes, computed in bulk over many steps.

At a team's size one step's counts (transmissions, deliveries, detections, the detector's
confusion counts, ...) are a couple of dozen numpy calls on a few hundred links, whose fixed
cost exceeds their arithmetic. :class:`OutcomeCounter` keeps each step's outcomes as one
byte per link and counts a whole buffer of steps at once; the counts are the per-step ones
exactly (integers).
"""

from __future__ import annotations

import numpy as np

from resloc.experiments.recording import pack_outcomes

__all__ = ["COUNTED", "OutcomeCounter", "per_group_counts"]

#: The per-trial totals the counter accumulates from the link outcomes.
COUNTED = (
    "triggered", "delivered", "detected", "failed", "fused", "attacked_fused", "tp", "fp", "fn",
    "tn", "repairs",
)  # fmt: skip
#: Bits of a link's byte: the recording's LINK_FLAGS first (so ``byte & 15`` is what the
#: recording keeps), then whether the update was repaired and whether the link was attacked.
_BITS = ("detected", "triggered", "delivered", "fused", "repaired", "attacked")
_LOG_MASK = np.uint8(0b1111)


def _flag(packed: np.ndarray, name: str) -> np.ndarray:
    """Flag ``name`` (one of :data:`_BITS`) of every link byte, bool (M,)."""
    return (packed & np.uint8(1 << _BITS.index(name))) != 0


def counted_masks(detected, triggered, delivered, fused, repaired, attacked) -> np.ndarray:
    """The :data:`COUNTED` outcomes of links with these flags (each (M,)), bool (11, M)."""
    return np.stack(
        (
            triggered,
            delivered,
            detected,
            triggered & ~delivered,
            fused,
            fused & attacked,
            detected & attacked,
            detected & ~attacked,
            ~detected & attacked,
            ~detected & ~attacked,
            repaired,
        )
    )


class _ByteCounts:
    """Per-group counts of the :data:`COUNTED` outcomes from the links' bytes: one
    ``bincount`` of (group, byte value) pairs times a table of what each of the 64 values
    of the :data:`_BITS` counts as (exact integers, several times faster than the 11
    masks' running sums)."""

    def __init__(self) -> None:
        values = np.arange(1 << len(_BITS), dtype=np.uint8)
        bits = np.unpackbits(values[None, :], axis=0, count=len(_BITS), bitorder="little")
        self.table = counted_masks(*bits.astype(bool)).T.astype(np.int64)  # (64, 11)
        self.mask = np.uint8((1 << len(_BITS)) - 1)

    def count(self, packed: np.ndarray, group: np.ndarray, groups: int) -> np.ndarray:
        """Counts ``(len(COUNTED), groups)`` of links with bytes ``packed`` in groups
        ``group`` (each (M,), values in ``[0, groups)``)."""
        values = len(self.table)
        if groups * values > 8 * len(packed) + 65536:  # many groups, few links: the masks
            bits = (packed[None, :] >> np.arange(len(_BITS), dtype=np.uint8)[:, None]) & 1
            return per_group_counts(counted_masks(*bits.astype(bool)), group, groups)
        key = group.astype(np.int64) * values + (packed & self.mask)
        per_value = np.bincount(key, minlength=groups * values).reshape(groups, values)
        return (per_value @ self.table).T


_COUNTS_OF_BYTE = _ByteCounts()


def per_group_counts(masks: np.ndarray, group: np.ndarray, groups: int) -> np.ndarray:
    """How many entries of each group every row of ``masks`` marks.

    Parameters
    ----------
    masks : ndarray of bool, shape (K, M)
    group : ndarray of int, shape (M,)
        Values in ``[0, groups)``.
    groups : int

    Returns
    -------
    ndarray of int64, shape (K, groups)
        ``np.bincount(group, weights=row, minlength=groups)`` of every row.
    """
    K, M = masks.shape
    if groups == 1:
        return np.count_nonzero(masks, axis=1).astype(np.int64)[:, None]
    if M and np.all(group[1:] >= group[:-1]):  # sorted (steps in order, links by trial)
        # Running counts along each row, read at the groups' boundaries.
        bounds = np.searchsorted(group, np.arange(groups + 1))
        # int32 running counts while they cannot overflow: numpy's bool -> int64 cumsum
        # goes through a casting loop at about twice the time.
        dtype = np.int32 if M < 2**31 - 1 else np.int64
        running = np.zeros((K, M + 1), dtype)
        flags = masks.view(np.uint8) if masks.dtype == np.bool_ else masks
        np.cumsum(flags, axis=1, dtype=dtype, out=running[:, 1:])
        return (running[:, bounds[1:]] - running[:, bounds[:-1]]).astype(np.int64)
    return np.stack([np.bincount(group[m], minlength=groups) for m in masks]).astype(np.int64)


def _distinct_per_trial(keys: np.ndarray, trial: np.ndarray, trials: int) -> np.ndarray:
    """How many distinct ``keys`` (int64, (M,)) each trial has; ``trial`` (M,) is a
    function of the key."""
    _, first = np.unique(keys, return_index=True)
    return np.bincount(trial[first], minlength=trials)


class OutcomeCounter:
    """One estimator's per-step link outcomes, counted per trial in bulk.

    :meth:`add` keeps a step's outcomes (one byte per link) and the world's per-step
    arrays it needs (references, not copies); :meth:`flush` counts the buffered steps and
    writes ``series`` rows ``candidates``, ``attacked``, ``triggered``, ``delivered``,
    ``detected``, adds to ``totals`` (:data:`COUNTED`, ``candidates``, ``attacked`` and,
    for a fusion that acknowledges fusions, ``ack_links`` and ``ack_frames``), fills the
    ``raster`` rows (transmissions per robot of trial 0) and appends trial 0's recorded
    flags to ``link_flags``. It flushes when :data:`MAX_ROWS` steps are buffered and when
    the series' last row is added; whoever reads the records earlier calls :meth:`flush`.

    Parameters
    ----------
    series, totals : dict of str to ndarray
        Shapes (steps, T) and (T,).
    raster : ndarray, shape (steps, N)
    link_flags : list of ndarray
        Receives trial 0's packed :data:`~resloc.experiments.recording.LINK_FLAGS`.
    trials, robots : int
        ``T`` and ``N``; robot ``b`` of a step's links is robot ``b % N`` of trial ``b // N``.
    acks : str or None
        The fusion acknowledges every fusion: count ``{acks}_links`` and ``{acks}_frames``
        (``"ack"``: gauge's blocks; ``"delivery_ack"``: split CI's ids).
    pairs : bool
        The fusion closes every pair that fused in either direction with a pair message
        (``factorized``): count, per trial, ``pair_ack_links`` / ``pair_ack_frames`` (the
        lower id tells the higher "I fused you", ids only) and ``pair_messages`` /
        ``pair_frames`` (the higher id sends the lower its ``[A, B, P_pred, sigma]``; the
        lower keeps the pair's cross-covariance: :meth:`resloc.cl.node.RobotNode.close_pairs`).
        :meth:`add` then needs the links' partners ``j``.
    """

    #: Most steps buffered (beyond it the fixed costs are already amortized).
    MAX_ROWS = 256

    def __init__(
        self, series, totals, raster, link_flags, trials, robots, acks=None, pairs=False
    ) -> None:
        self.series, self.totals, self.raster = series, totals, raster
        self.link_flags = link_flags
        self.trials, self.robots, self.acks = int(trials), int(robots), acks
        self.pairs = bool(pairs)
        self.last_row = len(series["candidates"]) - 1
        self.pending: list[tuple] = []

    def add(self, row, out, i, team_i, attacked, candidates, attacked_n, j=None) -> None:
        """Record step ``row``: ``out`` (a :class:`~resloc.cl.links.LinkOutcome`, or None
        when the estimator fuses nothing), the links' observers ``i``, their trials
        ``team_i`` and ``attacked`` flags (each (E,)), the step's per-trial
        ``candidates`` and ``attacked_n`` (T,), and the links' partners ``j`` (E,) (read
        only when counting ``pairs``)."""
        packed = None
        if out is not None:
            flags = (out.detected, out.triggered, out.delivered, out.fused, out.repaired)
            packed = pack_outcomes(*flags, attacked)
        self.pending.append((row, packed, i, team_i, candidates, attacked_n, j))
        if len(self.pending) >= self.MAX_ROWS or row == self.last_row:
            self.flush()

    def flush(self) -> None:
        """Count the buffered steps into the records."""
        if not self.pending:
            return
        pending, self.pending = self.pending, []
        T, N = self.trials, self.robots
        s, tot = self.series, self.totals
        rows = np.array([p[0] for p in pending])
        candidates = np.stack([p[4] for p in pending])
        attacked_n = np.stack([p[5] for p in pending])
        s["candidates"][rows] = candidates
        s["attacked"][rows] = attacked_n
        tot["candidates"] += candidates.sum(axis=0)
        tot["attacked"] += attacked_n.astype(np.int64).sum(axis=0)
        linked = [p for p in pending if p[1] is not None]
        if not linked:
            return
        rows = np.array([p[0] for p in linked])
        C = len(linked)
        sizes = np.array([len(p[1]) for p in linked])
        packed = np.concatenate([p[1] for p in linked])
        i = np.concatenate([p[2] for p in linked])
        team_i = np.concatenate([p[3] for p in linked])
        slot = np.repeat(np.arange(C), sizes)
        counts = _COUNTS_OF_BYTE.count(packed, slot * T + team_i, C * T)
        counts = counts.reshape(len(COUNTED), C, T)
        triggered, fused = _flag(packed, "triggered"), _flag(packed, "fused")
        counted = dict(zip(COUNTED, counts, strict=True))
        for key in ("triggered", "delivered", "detected"):
            s[key][rows] = counted[key]
        for key, per_step in counted.items():
            tot[key] += per_step.sum(axis=0)
        if self.acks:  # one acknowledgement per fusion, one frame per fusing robot
            tot[f"{self.acks}_links"] += counted["fused"].sum(axis=0)
            B = T * N
            senders = np.unique(slot[fused] * B + i[fused]) % B
            tot[f"{self.acks}_frames"] += np.bincount(senders // N, minlength=T)
        if self.pairs:
            j = np.concatenate([p[6] for p in linked])
            self._count_pairs(slot[fused], i[fused], j[fused], team_i[fused])
        own = i < N
        transmissions = np.bincount(
            slot[own] * N + i[own], weights=triggered[own], minlength=C * N
        ).reshape(C, N)
        self.raster[rows] = transmissions
        self.link_flags.append(packed[own] & _LOG_MASK)

    def _count_pairs(self, slot, i, j, trial) -> None:
        """Count the pair exchange of the fused links ``(i, j)`` of buffered steps ``slot``
        in trials ``trial`` (each (F,); ``i`` and ``j`` are in one trial, so their order is
        their ids' order)."""
        T = self.trials
        B = T * self.robots
        told = i < j  # the lower id fused the higher: the higher must hear of the pair
        tot = self.totals
        tot["pair_ack_links"] += np.bincount(trial[told], minlength=T)
        tot["pair_ack_frames"] += _distinct_per_trial(slot[told] * B + i[told], trial[told], T)
        low, high = np.minimum(i, j), np.maximum(i, j)
        tot["pair_messages"] += _distinct_per_trial((slot * B + low) * B + high, trial, T)
        tot["pair_frames"] += _distinct_per_trial(slot * B + high, trial, T)
