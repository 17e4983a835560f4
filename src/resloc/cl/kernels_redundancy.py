"""Compiled twins of the redundancy stage and its sequence test.

The redundancy stage (:mod:`resloc.cl.detection_redundancy`) and the sequence test on its
residuals (:mod:`resloc.cl.detection_sequence`) judge every link of a step once, at the
predicted estimates, before any update: their verdict does not depend on the order in which
the links are fused. The compiled correction therefore runs them as a pre-pass,
:func:`fix_verdicts`, one call over every observer's rows, which gives the link loops
(:mod:`resloc.cl.kernels_links`, :mod:`resloc.cl.kernels_rounds`) one flag per link
(:attr:`KernelDetection.fixes <resloc.cl.kernels_detection.KernelDetection>`): discard.
The sequence test's per-link state is the same store of the run's
:class:`~resloc.cl.memory.LinkMemory` the numpy stage reads and writes
(``stage_statistic("redundancy_sequence", width=6)``), updated in place; a run can switch
paths between steps. :meth:`~resloc.cl.kernels_detection.PrepassVerdict.undo` puts it back
when the kernel gives up on a step.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`claim_scales`           the scale of :func:`~resloc.cl.detection_redundancy.
                               weight_capped_covariance` and ``capped_claims``
                               (``_group_median``)
:func:`trace_scales`           the same from the rows' traces (``_group_median``)
:func:`position_fix_of_link`   :func:`~resloc.cl.detection_redundancy.position_fix`
                               (:func:`_fixes_of_block`: in SIMD lanes)
:func:`exclude_group`          :func:`~resloc.cl.detection_redundancy.exclude_inconsistent`
                               (``_reference``, ``_statistic``)
:func:`sequence_group`         :func:`~resloc.cl.detection_sequence.sequence_evidence`
                               (``sequence_step``)
:func:`fix_verdicts`           :func:`~resloc.cl.detection_redundancy.fix_evidence` and the
                               stages' ``discard``
=============================  ==========================================================

The kernels are compiled (or loaded from numba's cache) on the first step that switches
the stage on: a run without it does not pay for them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl.detection_sequence import WIDTH, RedundancySequence
from resloc.cl.kernels_detection import (
    DetectorState,
    PrepassVerdict,
    gain_at,
    shared_slots,
    store_slots,
)
from resloc.cl.kernels_lanes import SINCOS_LANES_MAX, sincos_lanes
from resloc.cl.kernels_math import (
    gain_array,
    jit,
    jit_inline,
    jit_lanes,
    per_params,
    stamp_with_pieces,
)
from resloc.cl.kernels_reciprocal import partner_readings
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "FixOptions",
    "capped_links",
    "claim_scales",
    "exclude_group",
    "fix_verdicts",
    "named_fix_options",
    "position_fix_of_link",
    "redundancy_verdict",
    "scaled_fix_verdicts",
    "scales_to_median",
    "sequence_group",
    "trace_scales",
]

#: A reference with no peer (twin: ``detection_redundancy._NO_PEER_COV``).
_NO_PEER_COV = 1e12
#: The sequence state's hold column (twin: ``detection_sequence._HOLD``).
_HOLD = 5


class FixOptions(NamedTuple):
    """The stages' options as :func:`fix_verdicts` takes them; gains ``(1,)`` or ``(B,)``."""

    R: np.ndarray  # (2, 2)
    gate: np.ndarray  # redundancy_gate
    min_peers: np.ndarray  # redundancy_min_peers
    sequence: bool  # redundancy_sequence
    sequence_gate: np.ndarray
    sequence_hold: np.ndarray
    sequence_forget: np.ndarray


_NO_GAIN = np.zeros(1)


@per_params
def _fix_options(params: CLParams) -> tuple:
    """:class:`FixOptions` of ``params`` as a plain tuple (numba types a NamedTuple
    argument in Python, a plain tuple by its fast fingerprint: ``kernels._plain``)."""
    return tuple(named_fix_options(params))


def named_fix_options(params: CLParams) -> FixOptions:
    """The stages' options of ``params`` (:class:`FixOptions`)."""
    sequence = bool(params.redundancy_sequence)
    seq = (
        tuple(
            gain_array(v)
            for v in (
                params.redundancy_sequence_gate,
                params.redundancy_sequence_hold,
                params.redundancy_sequence_forget,
            )
        )
        if sequence
        else (_NO_GAIN, _NO_GAIN, _NO_GAIN)
    )
    return FixOptions(
        np.ascontiguousarray(params.R, dtype=float),
        gain_array(params.redundancy_gate),
        gain_array(params.redundancy_min_peers),
        sequence,
        *seq,
    )


# ---------------------------------------------------------------------------------------
# Compiled pieces
# ---------------------------------------------------------------------------------------
@jit
def claim_scales(li, P_nb, nb, scale, scratch):
    """Per row ``e``: the factor ``max(m / t_e, 1)`` (1 where ``t_e <= 0``) with ``t_e``
    the trace of the position block of ``P_nb[nb[e]]`` and ``m`` the median of those traces
    over the rows of the same observer ``li[e]``, into ``scale: (E,)``. Rows must be sorted
    by observer (False otherwise; ``scratch``: (E,)). Twin: the scale of
    :func:`~resloc.cl.detection_redundancy.weight_capped_covariance` and
    :func:`~resloc.cl.detection_redundancy.capped_claims` (``_group_median``)."""
    E = li.shape[0]
    for e in range(E):  # the traces, once (the rows' own, then their factors, in scale)
        scale[e] = P_nb[nb[e], 0, 0] + P_nb[nb[e], 1, 1]
    return trace_scales(li, scale, scratch)


@jit_inline
def scales_to_median(scale, start, stop, median):
    """``scale[start:stop]``, a group's traces, replaced by ``max(median / t, 1)`` (1 where
    ``t <= 0`` or NaN; a NaN ratio stays NaN, as ``np.maximum``): the factor that raises
    each claim of the group to the group's median."""
    for e in range(start, stop):
        t = scale[e]
        s = 1.0
        if t > 0.0:
            s = median / t
            if s < 1.0:  # np.maximum: a NaN stays NaN
                s = 1.0
        scale[e] = s


@jit_inline
def trace_scales(li, scale, scratch):
    """:func:`claim_scales` from the rows' traces, given in ``scale: (E,)`` and replaced by
    their factors (for callers that hold the claims per row: no index array)."""
    E = li.shape[0]
    start = 0
    while start < E:
        if start > 0 and li[start] < li[start - 1]:
            return False
        stop = start + 1
        while stop < E and li[stop] == li[start]:
            stop += 1
        count = stop - start
        for e in range(start, stop):  # insertion sort of the group's traces (a few rows)
            t = scale[e]
            k = e
            while k > start and scratch[k - 1] > t:
                scratch[k] = scratch[k - 1]
                k -= 1
            scratch[k] = t
        median = 0.5 * (scratch[start + (count - 1) // 2] + scratch[start + count // 2])
        scales_to_median(scale, start, stop, median)
        start = stop
    return True


@jit_inline
def position_fix_of_link(
    z0, c, s, xo0, xo1, var_heading, grow, xn0, xn1, p00, p01, p10, p11, r00, r01, r10, r11
):  # fmt: skip
    """Observer i's position as link ``(i, j)`` says, ``f = p_j - r u(theta_i + b)``, and
    its covariance ``C``, symmetrized, as the entries ``(a, b, c)`` of ``[[a, b], [b, c]]``
    from j's credited position covariance ``[[p00, p01], [p10, p11]]``, i's heading variance
    and the sensor noise ``R = [[r00, r01], [r10, r11]]``: ``(f0, f1, C_a, C_b, C_c)``.
    ``(c, s)``: the cosine and sine of ``theta_i + b`` (:func:`fix_verdicts` computes them
    for every row at once). ``grow``: the range's mean correction ``exp((R_bb +
    var_heading) / 2)`` (one per observer: the caller computes it once for the observer's
    rows). Scalars only, no branch (:func:`_fixes_of_block` runs it over SIMD lanes). Twin:
    :func:`~resloc.cl.detection_redundancy.position_fix` (same operations, same order,
    but for ``np.hypot``, here the square root of the sum of squares, and ``np.cos``,
    ``np.sin``, the caller's polynomials: within a few ulps, no libm call; measured, the
    pass 16.2 -> 12.6 us a step of 260 links)."""
    r = z0
    r_mean = r * grow
    f0 = xn0 - r_mean * c
    f1 = xn1 - r_mean * s
    rel0 = xn0 - xo0
    rel1 = xn1 - xo1
    r_pred = math.sqrt(rel0 * rel0 + rel1 * rel1)  # (np.hypot's, within an ulp)
    known = r_pred > 0.0  # (selects, not a branch: the lanes' loop stays vectorized)
    c = rel0 / r_pred if known else c
    s = rel1 / r_pred if known else s
    r = r_pred if known else r
    ja0 = r * s
    ja1 = r * -c
    # J_z = [[-c, ja0], [-s, ja1]]; J_z R J_z^T as numpy's matmul of 2 x 2 matrices
    t00 = -c * r00 + ja0 * r10
    t01 = -c * r01 + ja0 * r11
    t10 = -s * r00 + ja1 * r10
    t11 = -s * r01 + ja1 * r11
    n00 = t00 * -c + t01 * ja0
    n01 = t00 * -s + t01 * ja1
    n10 = t10 * -c + t11 * ja0
    n11 = t10 * -s + t11 * ja1
    c00 = p00 + ja0 * ja0 * var_heading + n00
    c01 = p01 + ja0 * ja1 * var_heading + n01
    c10 = p10 + ja1 * ja0 * var_heading + n10
    c11 = p11 + ja1 * ja1 * var_heading + n11
    return f0, f1, 0.5 * (c00 + c00), 0.5 * (c01 + c10), 0.5 * (c11 + c11)


@jit_inline
def _information(a, b, c):
    """``[[a, b], [b, c]]^-1`` in closed form (twin: ``detection_redundancy._information``)."""
    det = a * c - b * b
    return c / det, -b / det, a / det


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
    information ``C^-1`` (entries) and ``C^-1 fix`` (:func:`_information`), ``residual: (2,
    E)``, ``ref_cov: (3, E)``. Twin: :func:`~resloc.cl.detection_redundancy.
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


#: Rows of :func:`fix_verdicts`' blocks (:func:`_fixes_of_block`): a fixed width, so that
#: the rows of the flat blocks lie a compile-time constant apart and LLVM proves the rows'
#: stores independent and vectorizes the loop (with the rows ``E`` apart it did not: a step
#: of 260 rows' fixes 3.8 -> 0.9 us measured on their own).
FIX_BLOCK = 64
# the rows of a block's inputs: range, cos, sin of theta_i + b, i's position and heading
# variance, the range's correction, j's position, j's credited covariance, theta_i + b
_RANGE, _COS, _SIN, _XO0, _XO1, _VAR_H, _GROW = 0, 1, 2, 3, 4, 5, 6
_XN0, _XN1, _P00, _P01, _P10, _P11, _ANGLE = 7, 8, 9, 10, 11, 12, 13
_FIX_INPUTS = 14
#: the rows of its results: the fix, its covariance's entries, the information's entries
#: and the information times the fix (:func:`exclude_group`'s ``fix``, ``cov``, ``info``)
_FIX_OUTPUTS = 10
#: :func:`fix_verdicts`' working rows (:func:`scaled_fix_verdicts`'): the claims' factors
#: and their scratch, the fixes, their covariances, their information, the statistics, the
#: residuals and their covariances
FIX_WORK_ROWS = 18


@jit_lanes
def _fixes_of_block(n, inputs, out, r00, r01, r10, r11):
    """Rows ``0 .. n - 1`` of a block: the sine and cosine of ``theta_i + b`` (by the
    branch-free polynomials in SIMD lanes; by libm out of their range), then each row's
    fix, its covariance (:func:`position_fix_of_link`) and its information
    (:func:`_information`), in a loop over rows that compiles to SIMD. ``inputs:
    (_FIX_INPUTS, FIX_BLOCK)``, ``out: (_FIX_OUTPUTS, FIX_BLOCK)``; ``R = [[r00, r01],
    [r10, r11]]``."""
    a = inputs.reshape(inputs.size)
    b = out.reshape(out.size)
    B = FIX_BLOCK
    for c in range(n):
        sn, cs = sincos_lanes(a[_ANGLE * B + c])
        a[_COS * B + c] = cs
        a[_SIN * B + c] = sn
    for c in range(n):  # (the polynomials' range; nan)
        angle = a[_ANGLE * B + c]
        if not abs(angle) <= SINCOS_LANES_MAX:
            a[_COS * B + c] = math.cos(angle)
            a[_SIN * B + c] = math.sin(angle)
    for c in range(n):
        f0, f1, ca, cb, cc = position_fix_of_link(
            a[_RANGE * B + c], a[_COS * B + c], a[_SIN * B + c], a[_XO0 * B + c],
            a[_XO1 * B + c], a[_VAR_H * B + c], a[_GROW * B + c], a[_XN0 * B + c],
            a[_XN1 * B + c], a[_P00 * B + c], a[_P01 * B + c], a[_P10 * B + c],
            a[_P11 * B + c], r00, r01, r10, r11,
        )  # fmt: skip
        Ya, Yb, Yc = _information(ca, cb, cc)  # once per row, not per exclusion round
        b[c] = f0
        b[B + c] = f1
        b[2 * B + c] = ca
        b[3 * B + c] = cb
        b[4 * B + c] = cc
        b[5 * B + c] = Ya
        b[6 * B + c] = Yb
        b[7 * B + c] = Yc
        b[8 * B + c] = Ya * f0 + Yb * f1
        b[9 * B + c] = Yb * f0 + Yc * f1


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
    """:func:`fix_verdicts` given the claims' factors (:func:`claim_scales`') in
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
    # the rows' fixes by blocks: each block's inputs gathered, its fixes in SIMD lanes
    # (_fixes_of_block), its results copied out by component
    B = FIX_BLOCK
    block = np.empty((_FIX_INPUTS + _FIX_OUTPUTS, B))
    inputs = block[:_FIX_INPUTS]
    out = block[_FIX_INPUTS:]
    grow = 1.0
    for start in range(0, E, B):
        n = min(B, E - start)
        for c in range(n):
            e = start + c
            i = li[e]
            m = nb[e]
            f = scale[e]
            if e == 0 or i != li[e - 1]:  # the observer's range correction, once
                grow = math.exp(0.5 * (R[1, 1] + P[i, 2, 2]))
            inputs[_RANGE, c] = z[e, 0]
            inputs[_XO0, c] = x[i, 0]
            inputs[_XO1, c] = x[i, 1]
            inputs[_VAR_H, c] = P[i, 2, 2]
            inputs[_GROW, c] = grow
            inputs[_XN0, c] = x_nb[m, 0]
            inputs[_XN1, c] = x_nb[m, 1]
            inputs[_P00, c] = P_nb[m, 0, 0] * f
            inputs[_P01, c] = P_nb[m, 0, 1] * f
            inputs[_P10, c] = P_nb[m, 1, 0] * f
            inputs[_P11, c] = P_nb[m, 1, 1] * f
            inputs[_ANGLE, c] = x[i, 2] + z[e, 1]
            # a link the sequence test holds out enters no reference (held_out)
            included[e] = not (sequence and seq_state[seq_slot[e], _HOLD] > 0.0)
        _fixes_of_block(n, inputs, out, R[0, 0], R[0, 1], R[1, 0], R[1, 1])
        for c in range(n):
            e = start + c
            fix[0, e] = out[0, c]
            fix[1, e] = out[1, c]
            cov[0, e] = out[2, c]
            cov[1, e] = out[3, c]
            cov[2, e] = out[4, c]
            for k in range(5):
                info[k, e] = out[5 + k, c]
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


# ---------------------------------------------------------------------------------------
# The dispatch's side (called by resloc.cl.kernels.fast_correct)
# ---------------------------------------------------------------------------------------
_NO_STATE = np.zeros((0, WIDTH))
_NO_SLOTS = np.zeros(0, np.int64)


_CLAIMS: list = []


def _claims():
    """:mod:`resloc.cl.kernels_claims` (it imports :func:`claim_scales`), imported on
    first use and kept (an import statement a step: ~0.5 us)."""
    if not _CLAIMS:
        from resloc.cl import kernels_claims

        _CLAIMS.append(kernels_claims)
    return _CLAIMS[0]


def capped_links(
    filt, x, P, links: LinkBatch, params: CLParams, strategy, memory
) -> LinkBatch | None:
    """``links`` as the reference's correction judges them with the redundancy stage on:
    the claimed covariances capped (``redundancy_cap_fusion``) and those of neighbours
    inside the landmark map weakened (``zone_landmarks``), both by one compiled pass
    (:func:`~resloc.cl.kernels_claims.claimed_links`), then an adversary's tamper
    hook applied to every row at the predicted estimates
    (:func:`~resloc.cl.kernels_reciprocal.partner_readings`, as the reference does: the
    hook is Python). None when the rows are not sorted by observer (the reference path
    then judges them). Twin: the head of ``resloc.cl.step._correct_reference``."""
    if params.redundancy_cap_fusion or params.zone_landmarks:
        links = _claims().claimed_links(params, links)
        if links is None:
            return None
    if links.tamper is not None:  # (with the hook's ``reported`` partner readings)
        links = partner_readings(filt, x, P, links, strategy, memory, params.R)
    return links


def redundancy_verdict(
    params, memory, li, lj, z, x, P, x_nb, P_nb, nb, detection
) -> PrepassVerdict | None:
    """The pre-pass of one step (:func:`fix_verdicts`): ``li``, ``lj`` int64 ``(E,)``,
    ``z: (E, 2)`` the readings as reported, ``x``, ``P`` the predicted estimates, ``x_nb``,
    ``P_nb`` the claimed estimates at rows ``nb`` (contiguous); ``detection``: the step's
    :class:`~resloc.cl.kernels_detection.KernelDetection` (the NIS CUSUM's store holds the
    same links as the sequence test's in a run's steady state: its slots are reused). None
    when the sequence test is on without the redundancy stage or has no memory to keep its
    state in, or the rows are not sorted by observer (the reference path then raises the
    explanatory error, or judges them)."""
    if not params.redundancy:
        return None  # the sequence test without its residuals: the reference explains
    options = _fix_options(params)
    saved: list = []
    state, slots = _NO_STATE, _NO_SLOTS
    if options[3]:  # FixOptions.sequence
        if memory is None:
            return None
        store = memory.stage_statistic(RedundancySequence.name, width=WIDTH)
        slots = None
        if detection.cusum:  # both stores hold every link of every step
            slots = shared_slots(store, memory.cusum, detection.cusum_slot, saved)
        if slots is None:
            slots = store_slots(store, li, lj, saved)
        state = store.values
    verdict = PrepassVerdict(np.zeros(len(li), dtype=np.bool_), DetectorState(None, tuple(saved)))
    x = np.ascontiguousarray(x, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    if not fix_verdicts(li, np.ascontiguousarray(z, dtype=float), x, P, x_nb, P_nb, nb, options,
                        state, slots, verdict.discard):  # fmt: skip
        verdict.undo()
        return None
    return verdict
