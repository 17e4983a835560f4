"""The redundancy stage and its sequence test judged, compiled: the pre-pass's verdict
kernels (twins of :mod:`resloc.cl.detection_redundancy` and
:mod:`resloc.cl.detection_sequence`).

:func:`fix_verdicts` judges every link of a step once, at the predicted estimates, from
the links' position fixes (:mod:`resloc.cl.kernels_redundancy_fixes`): fault exclusion per
observer, then the sequence test on the residuals, whose per-link state is the store of
the run's :class:`~resloc.cl.memory.LinkMemory` the numpy stage reads and writes (updated
in place). The dispatch's side is :mod:`resloc.cl.kernels_redundancy`.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`exclude_group`          :func:`~resloc.cl.detection_redundancy_exclusion.
                               exclude_inconsistent` (``_reference``, ``_statistic``)
:func:`sequence_group`         :func:`~resloc.cl.detection_sequence.sequence_evidence`
                               (``sequence_step``)
:func:`fix_verdicts`           :func:`~resloc.cl.detection_redundancy.fix_evidence` and the
                               stages' ``discard``
=============================  ==========================================================
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl.kernels_detection import gain_at
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces
from resloc.cl.kernels_redundancy_fixes import claim_scales, fixes_of_rows

__all__ = [
    "FIX_WORK_ROWS",
    "exclude_group",
    "fix_verdicts",
    "scaled_fix_verdicts",
    "sequence_group",
]

#: A reference with no peer (twin: ``detection_redundancy_exclusion._NO_PEER_COV``).
_NO_PEER_COV = 1e12
#: The sequence state's hold column (twin: ``detection_sequence._HOLD``).
_HOLD = 5


@jit_inline
def exclude_group(start, stop, fix, cov, info, included, gate, min_peers, stat, residual,
                  ref_cov):  # fmt: skip
    """Fault exclusion over one observer's rows ``start:stop``: while a row with at least
    ``min_peers`` included peers has a leave-one-out statistic above ``gate``, the worst such
    row is excluded (``included`` updated). Then per row: ``stat`` (``nan``: not judged),
    ``residual`` ``fix - m_-j`` (``nan``: not judged) and ``ref_cov``, the entries of
    ``C_j + (sum_{k != j} C_k^-1)^-1``. Arrays by component, rows last (each round's pass
    over the rows has no branch and numba vectorizes it: 4x faster than by row):
    ``fix: (2, E)``, ``cov: (3, E)`` (entries ``a, b, c``), ``info: (5, E)`` each row's
    information ``C^-1`` (entries) and ``C^-1 fix``
    (:func:`~resloc.cl.kernels_redundancy_fixes.fixes_of_rows`), ``residual: (2, E)``,
    ``ref_cov: (3, E)``. Twin: :func:`~resloc.cl.detection_redundancy_exclusion.
    exclude_inconsistent` (``_reference`` and ``_statistic`` on one group, the same
    operations: an excluded row's information times 0; groups are independent there too;
    IEEE division, as numpy's: inlined into :func:`fix_verdicts`, ``jit_lanes``; a call
    per observer of this and :func:`sequence_group` passed their arrays, whose reference
    counts cost ~0.6 us a step)."""
    while True:
        Sa = 0.0
        Sb = 0.0
        Sc = 0.0
        sa = 0.0
        sb = 0.0
        count = 0.0
        for e in range(start, stop):  # the group's information sums, in row order
            if included[e]:
                Sa += info[0, e]
                Sb += info[1, e]
                Sc += info[2, e]
                sa += info[3, e]
                sb += info[4, e]
                count += 1.0
        for e in range(start, stop):  # every row against its leave-one-out reference
            w = 1.0 if included[e] else 0.0
            Ya = info[0, e] * w
            Yb = info[1, e] * w
            Yc = info[2, e] * w
            ya = info[3, e] * w
            yb = info[4, e] * w
            ra = Sa - Ya
            rb = Sb - Yb
            rc = Sc - Yc
            peers = count - w
            has = peers > 0.0
            det = ra * rc - rb * rb
            Qa = rc / det if has else _NO_PEER_COV
            Qb = -rb / det if has else 0.0
            Qc = ra / det if has else _NO_PEER_COV
            f0 = fix[0, e]
            f1 = fix[1, e]
            m0 = Qa * (sa - ya) + Qb * (sb - yb) if has else f0
            m1 = Qb * (sa - ya) + Qc * (sb - yb) if has else f1
            a = cov[0, e] + Qa
            b = cov[1, e] + Qb
            c = cov[2, e] + Qc
            d0 = f0 - m0
            d1 = f1 - m1
            t = (c * d0 * d0 - 2.0 * b * d0 * d1 + a * d1 * d1) / (a * c - b * b)
            judged = peers >= min_peers
            stat[e] = t if judged else math.nan
            residual[0, e] = d0 if judged else math.nan
            residual[1, e] = d1 if judged else math.nan
            ref_cov[0, e] = a
            ref_cov[1, e] = b
            ref_cov[2, e] = c
        worst = -1
        worst_stat = 0.0
        for e in range(start, stop):  # (a row not judged has stat nan: never above)
            t = stat[e]
            if included[e] and t > gate and (worst < 0 or t > worst_stat):
                worst = e
                worst_stat = t
        if worst < 0:
            return
        included[worst] = False


@jit_inline
def sequence_group(start, stop, residual, ref_cov, state, slot, gate, hold, forget, discard):
    """The sequence test on one observer's rows ``start:stop`` from the redundancy residuals
    ``residual: (2, E)`` (``nan``: not judged) and their covariances ``ref_cov: (3, E)``
    (entries ``a, b, c``): each link's sums
    ``s <- lambda s + d``, ``V <- lambda^2 V + C_d`` since its admission, the one link of
    the observer with the largest ``s^T V^-1 s`` above ``gate`` held out for ``hold``
    evaluations (the other links' sums reset), a held link's hold counted down. The links'
    states ``state[slot[e]]`` (``[s_x, s_y, V_a, V_b, V_c, hold]``) are updated in place;
    ``discard[e]`` set where the link is held out. Twin:
    :func:`~resloc.cl.detection_sequence.sequence_evidence` (with ``sequence_step``) and
    ``RedundancySequence.discard``'s store (inlined into :func:`fix_verdicts`, as
    :func:`exclude_group`)."""
    alarm = -1
    alarm_stat = 0.0
    for e in range(start, stop):
        k = slot[e]
        d0 = residual[0, e]
        d1 = residual[1, e]
        holding = state[k, _HOLD] > 0.0
        update = math.isfinite(d0) and math.isfinite(d1) and not holding
        discard[e] = holding
        if holding:
            state[k, _HOLD] = state[k, _HOLD] - 1.0
        if not update:
            continue
        lam = forget
        s0 = lam * state[k, 0] + d0
        s1 = lam * state[k, 1] + d1
        Va = lam * lam * state[k, 2] + ref_cov[0, e]
        Vb = lam * lam * state[k, 3] + ref_cov[1, e]
        Vc = lam * lam * state[k, 4] + ref_cov[2, e]
        state[k, 0] = s0
        state[k, 1] = s1
        state[k, 2] = Va
        state[k, 3] = Vb
        state[k, 4] = Vc
        det = Va * Vc - Vb * Vb
        if det > 0.0:
            t = (Vc * (s0 * s0) - 2.0 * Vb * s0 * s1 + Va * (s1 * s1)) / det
            if t > gate and (alarm < 0 or t > alarm_stat):
                alarm = e
                alarm_stat = t
    if alarm < 0:
        return
    for e in range(start, stop):  # sums accumulated against references that held the lie
        if not discard[e] and math.isfinite(residual[0, e]) and math.isfinite(residual[1, e]):
            for a in range(5):
                state[slot[e], a] = 0.0
    state[slot[alarm], _HOLD] = hold
    discard[alarm] = True


#: :func:`fix_verdicts`' working rows (:func:`scaled_fix_verdicts`'): the claims' factors
#: and their scratch, the fixes, their covariances, their information, the statistics, the
#: residuals and their covariances
FIX_WORK_ROWS = 18


@jit_lanes
def fix_verdicts(li, z, x, P, x_nb, P_nb, nb, options, seq_state, seq_slot, discard):
    """The redundancy stage (and, with ``options.sequence``, its sequence test) on every
    link of one step at the predicted estimates ``x: (B, 3)``, ``P: (B, 3, 3)``: link
    ``e`` reads ``z[e]``, observer ``li[e]`` and j's claimed estimate ``x_nb[nb[e]]``,
    ``P_nb[nb[e]]``; ``discard: (E,)`` receives the verdict. ``seq_state[seq_slot[e]]``:
    the sequence test's state of link ``e`` (updated in place). Rows sorted by observer
    (False otherwise, nothing written). IEEE division, as numpy's (``jit_lanes``). Twin:
    :func:`~resloc.cl.detection_redundancy.fix_evidence` with ``RedundancyCheck.discard``
    and ``RedundancySequence.discard``."""
    work = np.empty((FIX_WORK_ROWS, li.shape[0]))
    if not claim_scales(li, P_nb, nb, work[0], work[1]):
        return False
    scaled_fix_verdicts(li, z, x, P, x_nb, P_nb, nb, options, seq_state, seq_slot, discard, work)
    return True


@jit_lanes
def scaled_fix_verdicts(
    li, z, x, P, x_nb, P_nb, nb, options, seq_state, seq_slot, discard, work
):  # fmt: skip
    """:func:`fix_verdicts` given the claims' factors
    (:func:`~resloc.cl.kernels_redundancy_fixes.claim_scales`') in
    ``work[0]``: ``work: (FIX_WORK_ROWS, E)`` its working arrays by component, rows of one
    allocation (a step made eleven); rows sorted by observer (the caller's test)."""
    R, gate, min_peers, sequence, seq_gate, seq_hold, seq_forget = options
    E = li.shape[0]
    scale = work[0]
    fix = work[2:4]  # by component (exclude_group)
    cov = work[4:7]
    info = work[7:12]
    stat = work[12]
    residual = work[13:15]
    ref_cov = work[15:18]
    included = np.empty(E, np.bool_)
    fixes_of_rows(li, z, x, P, x_nb, P_nb, nb, scale, R, fix, cov, info)
    for e in range(E):  # a link the sequence test holds out enters no reference (held_out)
        included[e] = not (sequence and seq_state[seq_slot[e], _HOLD] > 0.0)
    start = 0
    while start < E:
        stop = start + 1
        while stop < E and li[stop] == li[start]:
            stop += 1
        i = li[start]
        exclude_group(
            start, stop, fix, cov, info, included, gain_at(gate, i), gain_at(min_peers, i),
            stat, residual, ref_cov,
        )  # fmt: skip
        if sequence:
            sequence_group(
                start, stop, residual, ref_cov, seq_state, seq_slot, gain_at(seq_gate, i),
                gain_at(seq_hold, i), gain_at(seq_forget, i), discard,
            )  # fmt: skip
        else:
            for e in range(start, stop):
                discard[e] = False
        for e in range(start, stop):
            discard[e] = discard[e] or not included[e]
        start = stop


stamp_with_pieces(fix_verdicts, _kernels_detection, _kernels_lanes)
stamp_with_pieces(scaled_fix_verdicts, _kernels_detection, _kernels_lanes)
