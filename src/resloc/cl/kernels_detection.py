"""Compiled twins of the detector stages that keep per-link state (:mod:`resloc.cl.detection`).

The NIS CUSUM (:class:`~resloc.cl.detection.NISCusum`) and the mean-shift CUSUM
(:class:`~resloc.cl.detection.MeanShiftCusum`) remember a statistic per directed link in
:class:`~resloc.cl.memory.LinkStatistic` stores of the run's
:class:`~resloc.cl.memory.LinkMemory`. The compiled CL loop (:mod:`resloc.cl.kernels`)
reads and writes those stores in place: :func:`detector_state` gives it the stores' value
arrays and the slot of every link of the step (:meth:`LinkStatistic.slots
<resloc.cl.memory.LinkStatistic.slots>` inserts the links never seen, at 0, the value the
reference reads for them). When the kernel gives up on a step (a covariance that is not
positive definite), :meth:`DetectorState.undo` puts the stores back as they were, so the
reference path then starts from the same memory.

=============================  ========================================================
kernel function                numpy twin
=============================  ========================================================
:func:`nis_of`                   :func:`resloc.cl.cusum.nis`
:func:`nis_of_white`           :func:`resloc.cl.cusum.nis` (from :func:`whiten_of`'s result)
:func:`whiten_of`              :func:`resloc.cl.cusum.whiten`
:func:`cusum_step`             :func:`resloc.cl.cusum.link_cusum` (``cusum_update``,
                               ``cusum_alarm``) and ``NISCusum.discard``
:func:`mean_cusum_step`        :func:`resloc.cl.cusum.link_mean_cusum`
:func:`detect_link`           :func:`resloc.cl.detection.detect` (every active stage)
=============================  ========================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.detector import InnovationNorm
from resloc.cl.kernels_math import gain_array, jit_inline, per_params
from resloc.cl.kernels_memory import int64_rows, same_keys
from resloc.cl.kernels_stores import group_slots, keep_state, steady_state
from resloc.cl.kernels_zone import KernelZone, no_zone
from resloc.cl.kernels_zone_verdicts import SUBSTITUTED
from resloc.cl.params import CLParams

__all__ = [
    "DetectorState",
    "KernelDetection",
    "PrepassVerdict",
    "cusum_step",
    "detect_link",
    "detector_state",
    "mean_cusum_step",
    "shared_slots",
    "store_slots",
    "whiten_of",
]


class KernelDetection(NamedTuple):
    """The stateful detector stages as the kernel takes them.

    Gains are ``(1,)`` (one value) or ``(B,)`` (per observer); a stage that is off gets
    empty arrays, never read.
    """

    cusum: bool
    cusum_k: np.ndarray  # (1,) or (B,)
    cusum_h: np.ndarray
    cusum_cap: np.ndarray  # the statistic's bound (default 2 h)
    cusum_g: np.ndarray  # (n,) the store's values, written in place
    cusum_slot: np.ndarray  # (E,) int64, each link's position in cusum_g
    mean_cusum: bool
    mean_k: np.ndarray
    mean_h: np.ndarray
    mean_g: np.ndarray  # (n, 4): g+_r, g-_r, g+_b, g-_b, written in place
    mean_slot: np.ndarray  # (E,) int64
    # (E,) bool: the links the step's redundancy pre-pass discards
    # (resloc.cl.kernels_redundancy_verdicts.fix_verdicts); empty when the stage is off
    fixes: np.ndarray
    # zone-aware trust (resloc.cl.kernels_zone): its map, the partners' readings and each
    # row's verdict, written by the loop (KernelZone.on False when the stage is off)
    zone: KernelZone
    # (E,) bool: the links the witness stage discards (its neighbour convicted before the
    # step: resloc.cl.kernels_witness), on every row judged (substituted ones too); empty
    # when the stage is off
    witness: np.ndarray


class DetectorState(NamedTuple):
    """The kernel form of stateful stages (a :class:`KernelDetection`, or a
    :class:`~resloc.cl.kernels_defence.KernelDefence`) with what :meth:`undo` needs."""

    kernel: KernelDetection
    # per store: (store, keys before, values before or None, slots, a copy of all values
    # before or None): the arrays before when the step inserted links (they are left
    # untouched), else a copy of the values (all of them: one copy of a contiguous array
    # costs less than a gather at the step's slots, which repeat a robot's slot per link)
    saved: tuple

    def undo(self) -> None:
        """Put the stores back as they were before :func:`detector_state`."""
        for store, keys, values, _slots, old in self.saved:
            if values is not None:  # links were inserted: the old arrays are untouched
                store.keys, store.values = keys, values
            else:
                store.values[...] = old


class PrepassVerdict(NamedTuple):
    """A compiled pre-pass's discards, shape (E,), and its stage's state before the step
    (:func:`resloc.cl.kernels_redundancy_verdicts.fix_verdicts`,
    :func:`resloc.cl.kernels_reciprocal.reciprocal_verdict`)."""

    discard: np.ndarray
    state: DetectorState

    def undo(self) -> None:
        """Put the stage's store back as it was before the pre-pass."""
        self.state.undo()


_NO_GAIN = np.zeros(1)
_NO_SLOTS = np.zeros(0, np.int64)
_NO_FIXES = np.zeros(0, np.bool_)


def store_slots(store, i, j, saved: list) -> np.ndarray:
    """Slots of links ``(i, j)`` in ``store``'s values (:meth:`LinkStatistic.slots
    <resloc.cl.memory.LinkStatistic.slots>`), recording in ``saved`` what
    :meth:`DetectorState.undo` needs to put the store back."""
    keys, values = store.keys, store.values
    slots = store.slots(i, j)
    if store.values is values:
        saved.append((store, keys, None, slots, values.copy()))
    else:
        saved.append((store, keys, values, slots, None))
    if not store.values.flags.c_contiguous:
        store.values = np.ascontiguousarray(store.values)
    return slots


@per_params
def _detection_gains(params: CLParams) -> tuple:
    """``(cusum, k, h, cap, mean_cusum, mean_k, mean_h)`` as the kernel takes them."""
    cusum, mean = bool(params.cusum), bool(params.mean_cusum)
    k = h = cap = mk = mh = _NO_GAIN
    if cusum:
        h = gain_array(params.cusum_h)
        cap = 2.0 * h if params.cusum_cap is None else gain_array(params.cusum_cap)
        k = gain_array(params.cusum_k)
    if mean:
        mk, mh = gain_array(params.mean_cusum_k), gain_array(params.mean_cusum_h)
    return cusum, k, h, cap, mean, mk, mh


#: :func:`_same_keys`' answers by the pair of key arrays compared, each entry holding the
#: two arrays (so their ids are not reused while it stands). A store never changes its keys
#: in place (:meth:`LinkStatistic.slots <resloc.cl.memory.LinkStatistic.slots>` replaces
#: the array when it inserts, ``undo`` puts the old one back), so the same two arrays give
#: the same answer: a run's steady state compares the same pairs every step, five or six a
#: step with the full defence, ~0.9 us each.
_SAME_KEYS: dict = {}


def _same_keys(store, other) -> bool:
    a, b = store.keys, other.keys
    known = _SAME_KEYS.get((id(a), id(b)))
    if known is not None and known[0] is a and known[1] is b:
        return known[2]
    if a.shape != b.shape:
        same = False
    else:
        rows = int64_rows(a), int64_rows(b)
        if rows[0] is None or rows[1] is None:
            same = bool(np.array_equal(a, b))
        else:
            same = bool(same_keys(*rows))  # compiled (kernels_memory): 2-4% of a step in numpy
    if len(_SAME_KEYS) >= 64:  # (old pairs: the stores of finished runs)
        _SAME_KEYS.clear()
    _SAME_KEYS[(id(a), id(b))] = (a, b, same)
    return same


def _saved(store, slots: np.ndarray) -> tuple:
    """What :meth:`DetectorState.undo` needs to restore ``store`` at ``slots`` (in place)."""
    if not store.values.flags.c_contiguous:
        store.values = np.ascontiguousarray(store.values)
    return (store, store.keys, None, slots, store.values.copy())


def shared_slots(store, other, slots: np.ndarray, saved: list) -> np.ndarray | None:
    """``slots``, the positions of the step's links in ``other``'s values, when ``store``
    holds the same keys (stores that see every link of every step: then the same slots),
    recording in ``saved`` what :meth:`DetectorState.undo` needs; None otherwise."""
    if not _same_keys(store, other):
        return None
    saved.append(_saved(store, slots))
    return slots


def detector_state(params: CLParams, memory, i: np.ndarray, j: np.ndarray) -> DetectorState | None:
    """The stateful stages of ``params`` for the links ``(i, j)`` of one step.

    Parameters
    ----------
    params : CLParams
    memory : LinkMemory or None
    i, j : ndarray of int, shape (E,)
        Observers and neighbour ids (distinct pairs).

    Returns
    -------
    DetectorState or None
        None when a stage needs a memory and there is none (the reference path raises the
        explanatory error).
    """
    saved: list = []
    cusum, k, h, cap, mean, mk, mh = _detection_gains(params)
    if (cusum or mean) and memory is None:
        return None
    slot = mslot = stores = None
    if cusum or mean:  # one look-up and one save for both stores (kernels_stores)
        stores = (memory.cusum,) * cusum + (memory.mean_cusum,) * mean
        state = steady_state(stores, params, i, j)  # the last step's, looked up again
        if state is not None:
            return state
        slot = mslot = group_slots(stores, i, j, saved)
    if cusum:
        if slot is None:
            slot = store_slots(memory.cusum, i, j, saved)
        g = memory.cusum.values
    else:
        g, slot = np.zeros(0), _NO_SLOTS
    if mean:
        if mslot is None:
            mslot = shared_slots(memory.mean_cusum, memory.cusum, slot, saved) if cusum else None
        if mslot is None:
            mslot = store_slots(memory.mean_cusum, i, j, saved)
        mg = memory.mean_cusum.values
    else:
        mg, mslot = np.zeros((0, 4)), _NO_SLOTS
    kernel = KernelDetection(
        cusum, k, h, cap, g, slot, mean, mk, mh, mg, mslot, _NO_FIXES, no_zone(), _NO_FIXES
    )
    state = DetectorState(kernel, tuple(saved))
    if stores is not None:
        keep_state(stores, params, state, slot if cusum else mslot)
    return state


#: Innovation-norm codes shared with the kernels.
NORM_CODE = {InnovationNorm.EUCLIDEAN: 0, InnovationNorm.SCALED: 1, InnovationNorm.NIS: 2}
NIS_CODE = NORM_CODE[InnovationNorm.NIS]


# ---------------------------------------------------------------------------------------
# Per-link pieces, inlined into the CL loop of resloc.cl.kernels.
# ---------------------------------------------------------------------------------------
@jit_inline
def gain_at(gain, i):
    """A gain of observer ``i`` from a ``(1,)`` or ``(B,)`` array (twin: ``at_robots``)."""
    return gain[i] if gain.shape[0] > 1 else gain[0]


@jit_inline
def nis_of(nu0, nu1, l00, l10, l11):
    """``max(Lambda^T S^-1 Lambda, 0)`` with ``S = L L^T`` (twin: :func:`~resloc.cl.cusum.nis`,
    the same solve order as :func:`resloc.linalg.solve_spd`)."""
    y0 = nu0 / l00
    y1 = (nu1 - l10 * y0) / l11
    return nis_of_white(nu0, nu1, y0, y1, l00, l10, l11)


@jit_inline
def nis_of_white(nu0, nu1, y0, y1, l00, l10, l11):
    """:func:`nis_of` from the whitened innovation ``(y0, y1) = L^-1 Lambda``
    (:func:`whiten_of`'s, the same operations: the same bits), for a stage that has it."""
    w1 = y1 / l11
    w0 = (y0 - l10 * w1) / l00
    q = nu0 * w0 + nu1 * w1
    return q if q > 0.0 else 0.0


@jit_inline
def whiten_of(nu0, nu1, l00, l10, l11):
    """``w = L^-1 Lambda`` (twin: :func:`~resloc.cl.cusum.whiten`)."""
    w0 = nu0 / l00
    return w0, (nu1 - l10 * w0) / l11


@jit_inline
def cusum_step(g, stat, k, h, cap):
    """One step of Page's CUSUM of the NIS on one link from statistic ``g``: ``(g', discard)``
    with ``g' = min(max(0, g + NIS - k), cap)``; the stage discards while ``g' > h`` a
    measurement with ``NIS > k``. Scalars only (a loop over lanes calls it without passing
    arrays). Twin: :func:`~resloc.cl.cusum.link_cusum` and ``NISCusum.discard``."""
    v = g + stat - k
    if v < 0.0:
        v = 0.0
    if v > cap:
        v = cap
    return v, v > h and stat > k


@jit_inline
def _link_cusum(g, slot, stat, k, h, cap):
    """:func:`cusum_step` on the statistic ``g[slot]``, stored in place."""
    v, discard = cusum_step(g[slot], stat, k, h, cap)
    g[slot] = v
    return discard


@jit_inline
def _signed_step(g, s, k, cap):
    v = g + s - k
    if v < 0.0:
        v = 0.0
    if v > cap:
        v = cap
    return v


@jit_inline
def mean_cusum_step(g0, g1, g2, g3, w0, w1, k, h, passed):
    """The four signed CUSUMs ``(g+_r, g-_r, g+_b, g-_b)`` of the whitened innovation of one
    link, updated only when the gate ``passed`` the measurement: ``(g0', g1', g2', g3',
    discard)``; discard while a component alarms a measurement with ``|w_c| > k``. Scalars
    only. Twin: :func:`~resloc.cl.cusum.link_mean_cusum`."""
    cap = 2.0 * h
    if passed:
        g0 = _signed_step(g0, w0, k, cap)
        g1 = _signed_step(g1, -w0, k, cap)
        g2 = _signed_step(g2, w1, k, cap)
        g3 = _signed_step(g3, -w1, k, cap)
    alarm_r = g0 > h or g1 > h
    alarm_b = g2 > h or g3 > h
    return g0, g1, g2, g3, (alarm_r and abs(w0) > k) or (alarm_b and abs(w1) > k)


@jit_inline
def _link_mean_cusum(g, slot, w0, w1, k, h, passed):
    """:func:`mean_cusum_step` on the statistics ``g[slot]``, stored in place."""
    g0, g1, g2, g3, discard = mean_cusum_step(
        g[slot, 0], g[slot, 1], g[slot, 2], g[slot, 3], w0, w1, k, h, passed
    )
    g[slot, 0] = g0
    g[slot, 1] = g1
    g[slot, 2] = g2
    g[slot, 3] = g3
    return discard


@jit_inline
def detect_link(det, e, i, gated, nu0, nu1, n_det, det_norm, l00, l10, l11):
    """Every active stage on link ``e`` of observer ``i`` after the gate's verdict
    ``gated``: whether its measurement is discarded. Twin: :func:`resloc.cl.detection.detect`."""
    cusum, ck, ch, ccap, cg, cslot, mean, mk, mh, mg, mslot, fixes, zone, witness = det
    # the redundancy stages' verdict, judged before the loop (kernels_redundancy); not on
    # a row zone trust substituted (fused as the partner's fix, not as this reading)
    fixed = fixes.shape[0] > 0 and fixes[e]
    detected = gated or (fixed and not (zone[0] and zone[3][e] == SUBSTITUTED))
    if witness.shape[0] > 0 and witness[e]:  # the witness stage's, on every row
        detected = True
    if cusum:
        if det_norm == NIS_CODE:
            stat = n_det * n_det
        else:
            stat = nis_of(nu0, nu1, l00, l10, l11)
        if _link_cusum(cg, cslot[e], stat, gain_at(ck, i), gain_at(ch, i), gain_at(ccap, i)):
            detected = True
    if mean:
        w0, w1 = whiten_of(nu0, nu1, l00, l10, l11)
        if _link_mean_cusum(mg, mslot[e], w0, w1, gain_at(mk, i), gain_at(mh, i), not gated):
            detected = True
    return detected
