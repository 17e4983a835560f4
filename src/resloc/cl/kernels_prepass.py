"""The defences' passes before the link loop, in one compiled call per step.

With the redundancy stage on, the compiled correction runs up to four passes over a step's
links before its link loop, each a numba call of its own with its Python glue:

* the claims the correction fuses (:func:`~resloc.cl.kernels_claims.claimed_covariances`:
  the redundancy stage's cap and the zone landmarks),
* zone trust's partners' readings (:func:`~resloc.cl.kernels_zone.partner_readings`),
* the redundancy pre-pass (:func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`: its
  claims' factors, then :func:`~resloc.cl.kernels_redundancy_verdicts.scaled_fix_verdicts`),
* the reciprocal check's pre-pass (:func:`~resloc.cl.kernels_reciprocal.reciprocal_verdicts`).

None of them depends on the order in which the links are fused, and none on the others'
Python glue: :func:`prepass_rows` calls the four kernels in one compiled call, on arrays
packed once per ``params`` (:func:`_options`), and :func:`prepass` is its glue (the stores'
slots and ``undo`` records, as each stage's own dispatch keeps them). The kernels and their
order are the stages' own, so the values are the same bits as the stage-by-stage path's
(``resloc.cl.kernels.fast_correct`` takes that path where this one does not apply: an
adversary's tamper hook, partners' readings the batch carries, cached neighbour estimates;
the witness stage runs before it: without a hook its verdict reads nothing the call
changes).

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`prepass_rows`           the head of ``resloc.cl.step._correct_reference`` (the
                               claims, the partners' readings), ``fix_evidence`` and
                               ``reciprocal_evidence`` with their stages' ``discard``
=============================  ==========================================================

The kernel is compiled (or loaded from numba's cache) on the first step that runs the
redundancy stage: a run without it does not pay for it.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl.detection_reciprocal import STATE_WIDTH, ReciprocalCheck
from resloc.cl.detection_sequence import WIDTH, RedundancySequence
from resloc.cl.kernels_claims import (
    CLAIMS_RUNS,
    CLAIMS_UNCHANGED,
    claim_options,
    claimed_covariances,
    raised_trace_scales,
)
from resloc.cl.kernels_detection import DetectorState, PrepassVerdict, shared_slots, store_slots
from resloc.cl.kernels_math import jit, per_params, stamp_with_pieces
from resloc.cl.kernels_reciprocal import reciprocal_options, reciprocal_verdicts
from resloc.cl.kernels_redundancy import named_fix_options
from resloc.cl.kernels_redundancy_fixes import claim_scales
from resloc.cl.kernels_redundancy_verdicts import FIX_WORK_ROWS, scaled_fix_verdicts
from resloc.cl.kernels_zone import KernelZone, ZoneState, partner_readings
from resloc.cl.kernels_zone_verdicts import OUTSIDE
from resloc.cl.params import CLParams

__all__ = [
    "PREPASS_CLAIMED",
    "PREPASS_OK",
    "PREPASS_RUNS",
    "PREPASS_UNSORTED",
    "Prepass",
    "applies",
    "prepass",
    "prepass_rows",
]

#: :func:`prepass_rows`'s status: done (no claim changed), the rows not sorted by observer
#: (nothing written; the reference path then judges them, as each stage's pass would have
#: it), done with the claims changed (the loop reads the per-row claims it wrote).
PREPASS_OK = 0
PREPASS_UNSORTED = 1
PREPASS_CLAIMED = 2

#: How often :func:`prepass` ran the compiled pass (the tests read it).
PREPASS_RUNS = {"compiled": 0}

#: :func:`prepass_rows`' ``flags``: the cap, the landmarks' inflation, zone trust, the
#: sequence test, the reciprocal check, its variance ``2 sigma_r^2``, then ``R`` (4).
_CAP, _INFLATION, _ZONE, _SEQUENCE, _RECIPROCAL, _VARIANCE, _R = range(7)
#: Its ``gains``' rows: the redundancy stage's (``FixOptions``), the reciprocal check's.
_GATE, _MIN_PEERS, _SEQ_GATE, _SEQ_HOLD, _SEQ_FORGET = range(5)
_REC_GATE, _REC_SEQUENCE_GATE, _REC_HOLD, _REC_FORGET = range(5, 9)


@jit
def prepass_rows(
    li, lj, z, x, P, x_src, P_src, rows, flags, gains, claim_discs, rec_discs, seq_state,
    seq_slot, seq_old, rec_state, rec_slot, rec_old, x_out, P_out, z_rec, verdict, discard,
):  # fmt: skip
    """The passes before the link loop of one step, in the stage-by-stage path's order:
    link ``e`` (observer ``li[e]``, neighbour ``lj[e]``, reading ``z[e]``, the neighbour's
    transmitted estimate ``x_src[rows[e]]``, ``P_src[rows[e]]``; ``x``, ``P``: the
    predicted estimates)

    1. its claim (with the cap, or a map ``claim_discs: (Z, 3)``:
       :func:`~resloc.cl.kernels_claims.claimed_covariances`), into ``P_out: (E, 3, 3)``
       and the neighbours' estimates into ``x_out: (E, D)`` (``x_out[e] = x_src[rows[e]]``)
       where a claim changes (``PREPASS_CLAIMED``);
    2. with zone trust (``z_rec``, ``verdict`` of ``E`` rows; else empty), its partner's
       reading (:func:`~resloc.cl.kernels_zone.partner_readings`) into ``z_rec: (E, 2)``,
       and zone trust's verdicts ``(E,)`` set to ``OUTSIDE``;
    3. the redundancy pre-pass (:func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`; the
       sequence test's state ``seq_state[seq_slot[e]]``) into ``discard: (E,)``;
       with the cap alone, the claims' factors it starts with are read from the order of
       the claims' traces the cap sorted (:func:`~resloc.cl.kernels_claims.raised_trace_scales`,
       the values of a full sort) where the redundancy pre-pass sorts them again;
    4. with the reciprocal check (:func:`~resloc.cl.kernels_reciprocal.reciprocal_verdicts`,
       its map ``rec_discs``, its state ``rec_state[rec_slot[e]]``), ORed into ``discard``.

    The options packed (:func:`_options`: a numba call pays ~0.04 us an argument):
    ``flags`` the switches and scalars (``_CAP`` ... ``_R``), ``gains: (9, L)`` the gains
    (``_GATE`` ... ``_REC_FORGET``; a row of ``L = 1`` or per observer: ``gain_at``).
    First, ``seq_old``, ``rec_old`` (of the states' shapes, or empty: not asked) receive
    a copy of the states before the step (the ``undo`` records' values). Returns the
    status: ``PREPASS_UNSORTED``, nothing else written, when the rows are not sorted by
    observer; ``PREPASS_CLAIMED`` (the loop reads ``x_out``, ``P_out`` at rows
    ``arange(E)``) or ``PREPASS_OK`` (no claim changed: ``x_src``, ``P_src`` at ``rows``).
    The outputs are the caller's (kept from step to step: a new array returned costs
    ~0.2 us, and its Python objects more). Shapes and indices as the link loop checks
    them (the caller's ``_shapes_ok``). Twin: the stages' passes, each (the same kernels,
    the same order)."""
    if seq_old.shape[0] > 0:
        seq_old[...] = seq_state
    if rec_old.shape[0] > 0:
        rec_old[...] = rec_state
    cap = flags[_CAP] != 0.0
    zone = flags[_ZONE] != 0.0
    R = np.empty((2, 2))
    R[0, 0] = flags[_R]
    R[0, 1] = flags[_R + 1]
    R[1, 0] = flags[_R + 2]
    R[1, 1] = flags[_R + 3]
    E = li.shape[0]
    for e in range(1, E):
        if li[e] < li[e - 1]:
            return PREPASS_UNSORTED
    status = PREPASS_OK
    x_nb = x_src
    P_nb = P_src
    nb = rows
    work = np.empty((FIX_WORK_ROWS, E))  # (scaled_fix_verdicts')
    scaled = False  # the redundancy stage's factors of the claims in work[0]
    if cap or claim_discs.shape[0] > 0:  # (kernels_claims.claimed_rows)
        out = P_out
        scratch = np.empty((2, E))
        inside = claimed_covariances(
            li, x_src, P_src, rows, cap, claim_discs, flags[_INFLATION], out, scratch[0],
            scratch[1],
        )  # fmt: skip
        if cap and inside == 0:
            # the claims are the capped ones: their factors (claim_scales' of ``out``) from
            # the order of the traces before the cap (scratch[1]; the cap's factors in
            # scratch[0]), without a second sort (raised_trace_scales; NaN: sorted)
            raised = np.empty(E, np.bool_)
            for e in range(E):
                work[0, e] = out[e, 0, 0] + out[e, 1, 1]
                raised[e] = scratch[0, e] != 1.0
            scaled = raised_trace_scales(li, work[0], raised, scratch[1], work[1])
        if inside != CLAIMS_UNCHANGED:  # (sorted: tested above)
            for e in range(E):
                n = rows[e]
                for a in range(x_out.shape[1]):
                    x_out[e, a] = x_src[n, a]
            x_nb = x_out
            P_nb = out
            nb = np.arange(E)
            status = PREPASS_CLAIMED
    if zone:
        partner_readings(li, lj, z, z_rec)
        verdict[:] = OUTSIDE
    discard[:] = False
    options = (
        R, gains[_GATE], gains[_MIN_PEERS], flags[_SEQUENCE] != 0.0, gains[_SEQ_GATE],
        gains[_SEQ_HOLD], gains[_SEQ_FORGET],
    )  # fmt: skip
    if not scaled:  # (fix_verdicts': sorted, tested above)
        claim_scales(li, P_nb, nb, work[0], work[1])
    scaled_fix_verdicts(li, z, x, P, x_nb, P_nb, nb, options, seq_state, seq_slot, discard, work)
    if flags[_RECIPROCAL] != 0.0:  # (z_rec of shape (0, 2): the reverse links' readings)
        reciprocal_verdicts(
            li, lj, z, z_rec, x, x_nb, nb, flags[_VARIANCE], gains[_REC_GATE],
            gains[_REC_SEQUENCE_GATE], gains[_REC_HOLD], gains[_REC_FORGET], rec_discs,
            rec_state, rec_slot, discard,
        )  # fmt: skip
    return status


stamp_with_pieces(prepass_rows, _kernels_detection, _kernels_lanes)


# ---------------------------------------------------------------------------------------
# The dispatch's side (called by resloc.cl.kernels.fast_correct)
# ---------------------------------------------------------------------------------------
class Prepass(NamedTuple):
    """:func:`prepass`'s result: the neighbours' estimates the loop reads (``x_nb: (S,
    3)``, ``P_nb: (S, 3, 3)``, link ``e``'s at row ``nb[e]``), zone trust's state (None
    without it), the redundancy pre-pass's verdict and the reciprocal check's (None without
    it; its ``discard`` is the redundancy pre-pass's array, the union)."""

    x_nb: np.ndarray
    P_nb: np.ndarray
    nb: np.ndarray
    zone: ZoneState | None
    fixes: PrepassVerdict
    paired: PrepassVerdict | None


_NO_STATE = np.zeros((0, WIDTH))
_NO_SLOTS = np.zeros(0, np.int64)
_NO_RECIPROCAL_STATE = np.zeros((0, STATE_WIDTH))
_NO_DISCS = np.zeros((0, 3))
_NO_GAIN = np.zeros(1)


class _NoMemory:
    """The key of :func:`prepass`'s outputs without a memory (no stage that keeps state)."""


_NO_MEMORY = _NoMemory()


@per_params
def _options(params: CLParams) -> tuple | None:
    """``(flags, gains, claim_discs, rec_discs, sequence, reciprocal, zone, claims)``: the
    options of :func:`prepass_rows` packed, then the stages on (``zone``: zone trust's map,
    ``(Z, 3)``, or None; ``claims``: whether a claim can change); None when the gains are
    per observer with different lengths (the stages' own dispatch then runs them)."""
    claims, cap, claim_discs, inflation = claim_options(params)
    fix = named_fix_options(params)
    reciprocal = bool(params.reciprocal)
    variance, rec_gains, rec_discs = 1.0, (_NO_GAIN,) * 4, _NO_DISCS
    if reciprocal:
        variance, *rec_gains, rec_discs = reciprocal_options(params)
    rows = (fix.gate, fix.min_peers, fix.sequence_gate, fix.sequence_hold, fix.sequence_forget)
    rows += tuple(rec_gains)
    lengths = {len(g) for g in rows} - {1}
    if len(lengths) > 1:
        return None
    gains = np.empty((len(rows), lengths.pop() if lengths else 1))
    gains[...] = np.stack([np.broadcast_to(g, gains.shape[1:]) for g in rows])
    zone = None
    if params.zone_trust:  # (kernels_zone's discs)
        zone = np.ascontiguousarray(np.asarray(params.zone_trust_map, float).reshape(-1, 3))
    flags = np.array(
        [cap, inflation, zone is not None, fix.sequence, reciprocal, variance, *fix.R.reshape(4)],
        float,
    )
    return flags, gains, claim_discs, rec_discs, fix.sequence, reciprocal, zone, claims


#: Per memory, per store (by id): ``(the store, its keys, its values, the NIS CUSUM store's
#: keys, the buffer its values are saved in, the last ``undo`` record or None)`` while the
#: two stores hold the same keys (weak: a finished run's stores and buffers go with its
#: memory; the stores do not refer to their memory).
_BUFFERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _slots(store, memory, li, lj, detection, saved: list, empty: np.ndarray) -> tuple:
    """``(slots, buffer)``: the slots of the step's links in ``store`` and the buffer
    :func:`prepass_rows` saves its values in (``empty``: saved here), recording in ``saved``
    what ``undo`` needs. In a run's steady state the store holds the NIS CUSUM's keys: its
    slots (:func:`~resloc.cl.kernels_detection.shared_slots`), and a buffer kept from step
    to step (``undo`` runs within the step that saved) which the kernel fills (the numpy
    copy and the keys' comparison were ~1.5 us a store and step)."""
    if not detection.cusum:
        return store_slots(store, li, lj, saved), empty
    keys, values, other = store.keys, store.values, memory.cusum.keys
    buffers = _BUFFERS.get(memory)
    if buffers is None:
        buffers = _BUFFERS[memory] = {}
    kept = buffers.get(id(store))
    if kept is not None and kept[0] is store and kept[1] is keys and kept[2] is values:
        if kept[3] is other:  # the same arrays: the same keys, the same buffer
            slots, record = detection.cusum_slot, kept[5]
            if record is None or record[3] is not slots:  # (the record kept with its slots)
                record = (store, keys, None, slots, kept[4])
                buffers[id(store)] = (*kept[:5], record)
            saved.append(record)
            return slots, kept[4]
    slots = shared_slots(store, memory.cusum, detection.cusum_slot, saved)
    if slots is None:
        return store_slots(store, li, lj, saved), empty
    values = store.values  # (made contiguous by shared_slots)
    if values.dtype == np.float64 and values.shape[1:] == empty.shape[1:] and len(values):
        buffers[id(store)] = (store, keys, values, other, np.empty_like(values), None)
    return slots, empty


def applies(params: CLParams, links, cached: bool) -> bool:
    """Whether :func:`prepass` runs the step's passes (else the stages' own dispatch):
    the redundancy stage on, no tamper hook (with one, the witness stage's readings as
    reported come between the claims and the partners'), no partners' readings carried by
    the batch, the transmitted neighbour estimates."""
    return bool(
        params.redundancy
        and links.tamper is None
        and links.z_reciprocal is None
        and not cached
        and _options(params) is not None
    )


class _Outputs:
    """A memory's outputs of :func:`prepass_rows` for steps of ``E`` links, kept from step
    to step, with the Python objects built on them (the verdicts, zone trust's state),
    kept while their ``undo`` records are the same objects (a run's steady state:
    :func:`_slots`' records). Nothing outside a step keeps them: the loops and ``undo``
    read them within the step, the memory stores copies."""

    __slots__ = (
        "E", "P_out", "discard", "discs", "fixes", "paired", "rows", "verdict", "x_out",
        "z_rec", "zone",
    )  # fmt: skip

    def __init__(self, E: int, D: int, discs) -> None:
        self.E = E
        self.x_out = np.empty((E, D))
        self.P_out = np.empty((E, 3, 3))
        self.rows = np.arange(E, dtype=np.int64)
        Z = 0 if discs is None else E
        self.z_rec = np.empty((Z, 2))
        self.verdict = np.zeros(Z, np.int64)
        self.discard = np.zeros(E, np.bool_)
        self.discs = discs
        self.zone = None
        if discs is not None:
            self.zone = ZoneState(KernelZone(True, discs, self.z_rec, self.verdict))
        self.fixes = self.paired = None

    def verdict_of(self, kept, records: tuple) -> PrepassVerdict:
        """The verdict on ``discard`` with ``records``: ``kept`` when it has them."""
        if kept is not None and len(kept.state.saved) == len(records):
            for a, b in zip(kept.state.saved, records, strict=True):  # (not all(): 0.3 us)
                if a is not b:
                    break
            else:
                return kept
        return PrepassVerdict(self.discard, DetectorState(None, records))


#: Per memory: its :class:`_Outputs` (weak: a finished run's arrays go with its memory).
_OUTPUTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _outputs(memory, E: int, D: int, discs) -> _Outputs:
    kept = _OUTPUTS.get(memory)
    if kept is None or kept.E != E or kept.discs is not discs:
        kept = _OUTPUTS[memory] = _Outputs(E, D, discs)
    elif kept.x_out.shape[1] != D:
        kept.x_out = np.empty((E, D))
    return kept


def prepass(params, memory, li, lj, z, x, P, x_src, P_src, rows, detection) -> tuple | None:
    """The passes of one step (:func:`prepass_rows`): ``li``, ``lj`` int64 ``(E,)``, ``z:
    (E, 2)`` the readings, ``x``, ``P`` the predicted estimates, ``x_src``, ``P_src`` the
    transmitted estimates at rows ``rows`` (contiguous, checked by the caller);
    ``detection``: the step's :class:`~resloc.cl.kernels_detection.KernelDetection` (the
    stores' slots are the NIS CUSUM's when they hold the same links). None when a stage
    needs a memory and there is none, or the rows are not sorted by observer (the
    reference path then raises the explanatory error, or judges them). Else the fields of
    a :class:`Prepass` (a plain tuple: the NamedTuple's ``__new__`` is ~0.3 us), on
    arrays kept for the memory until its next step (:class:`_Outputs`)."""
    flags, gains, claim_discs, rec_discs, sequence, on, zoned, claims = _options(params)
    if memory is None:
        if sequence or on:
            return None
        memory = _NO_MEMORY
    saved: list = []
    seq_state, seq_slot, seq_old = _NO_STATE, _NO_SLOTS, _NO_STATE
    if sequence:
        store = memory.stage_statistic(RedundancySequence.name, width=WIDTH)
        seq_slot, seq_old = _slots(store, memory, li, lj, detection, saved, _NO_STATE)
        seq_state = store.values
    rec_saved: list = []
    rec_state, rec_slot, rec_old = _NO_RECIPROCAL_STATE, _NO_SLOTS, _NO_RECIPROCAL_STATE
    if on:
        store = memory.stage_statistic(ReciprocalCheck.name, width=STATE_WIDTH)
        rec_slot, rec_old = _slots(
            store, memory, li, lj, detection, rec_saved, _NO_RECIPROCAL_STATE
        )
        rec_state = store.values
    out = _outputs(memory, len(li), x_src.shape[1], zoned)
    status = prepass_rows(
        li, lj, z, x, P, x_src, P_src, rows, flags, gains, claim_discs, rec_discs, seq_state,
        seq_slot, seq_old, rec_state, rec_slot, rec_old, out.x_out, out.P_out, out.z_rec,
        out.verdict, out.discard,
    )  # fmt: skip
    PREPASS_RUNS["compiled"] += 1
    if claims:  # (the claims' pass, kernels_claims)
        CLAIMS_RUNS["compiled"] += 1
    fixes = out.fixes = out.verdict_of(out.fixes, tuple(saved))
    paired = None
    if on:
        paired = out.paired = out.verdict_of(out.paired, tuple(rec_saved))
    if status == PREPASS_UNSORTED:
        if paired is not None:
            paired.undo()
        fixes.undo()
        return None
    if status == PREPASS_CLAIMED:
        return out.x_out, out.P_out, out.rows, out.zone, fixes, paired
    return x_src, P_src, rows, out.zone, fixes, paired
