"""Compiled twin of the CL correction (:func:`resloc.cl.step.correct`): its dispatch.

:func:`fast_correct` prepares the inputs of one step and makes one call of the compiled link
loop (:func:`resloc.cl.kernels_links.correct_links`), which processes every link of a
:class:`~resloc.cl.links.LinkBatch` (all robots of all trials) in row order. Each piece of a
link's work is a named function beside the numpy function it twins (``docs/algorithm.md``
maps every equation to both; the scalar primitives are in :mod:`resloc.cl.kernels_math`):

============================  ======================  =============================================
kernel function               paper                   numpy twin
============================  ======================  =============================================
``correct_links`` (block)    eq. (3), Algorithm 1    ``SigmaPointFilter.relative_moments``
``_linearized_moments``       eq. (3), linearized     ``ExtendedFilter.relative_moments``
``_innovation_norm``          eq. (9), detector       :func:`resloc.cl.detector.innovation_norm`
``_event_threshold``          eq. (11)                :func:`resloc.cl.trigger.event_threshold`
``_gate_link``                Algorithm 1, detector   :func:`resloc.cl.detector.attack_detected`
``detect_link`` (CUSUMs)      beyond the paper        :func:`resloc.cl.detection.detect`
``defend_link``               beyond the paper        robot CUSUM and recovery stages
``fix_verdicts`` (pre-pass)   beyond the paper        redundancy stages (``fix_evidence``)
``reciprocal_verdicts``       beyond the paper        ``reciprocal_evidence`` (pre-pass)
``prepass_rows``              beyond the paper        the claims, zone's readings and the two
                                                      pre-passes above, in one call
``zone_verdict`` (+ fix)      beyond the paper        zone trust (``substitute_reciprocal``,
                                                      ``reciprocal_position_fix``)
``_decide_link``              Alg. 1, eqs. (8), (10)  ``resloc.cl.step._decide``
``_cached_decision``          eqs. (8), (10), cached  ``resloc.cl.step._decide`` (``cached``)
``correct_links`` (block)    Algorithm 1, gain       :func:`resloc.filters.update.kalman_gain`
``schur_update``              Algorithm 1             :func:`resloc.filters.update.kalman_update`
``joseph_update``             Algorithm 1 (EKF)       :func:`resloc.filters.update.kalman_update`
``ci_update``                 beyond the paper        :func:`resloc.cl.fusion.fused_update` (``ci``)
============================  ======================  =============================================

(in :mod:`resloc.cl.kernels_links`, :mod:`resloc.cl.kernels_detection`,
:mod:`resloc.cl.kernels_defence`, :mod:`resloc.cl.kernels_fusion`,
:mod:`resloc.cl.kernels_zone` and, imported only when their stages are on,
:mod:`resloc.cl.kernels_redundancy`, :mod:`resloc.cl.kernels_reciprocal`,
:mod:`resloc.cl.kernels_prepass`).

What the kernel covers is decided by :func:`resloc.cl.backend.kernel_refusal` from the
strategies; the inputs are named structures (:class:`KernelLinks`, :class:`KernelRobots`,
:class:`KernelOptions`, :class:`~resloc.cl.backend.FilterKernelSpec`,
:class:`~resloc.cl.kernels_detection.KernelDetection`, :class:`KernelOutputs`). The detector
stages that keep per-link state (the CUSUMs) are in :mod:`resloc.cl.kernels_detection`.
"""

from __future__ import annotations

import contextlib
import importlib
import weakref
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from resloc.cl.backend import (  # backend choice re-exported for callers of this module
    HAVE_NUMBA,
    FilterKernelSpec,
    backend,
    filter_kernel_spec,
    kernel_refusal,
    set_backend,
    use_backend,
)
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_checks import observer_bound
from resloc.cl.kernels_defence import defence_state
from resloc.cl.kernels_detection import NORM_CODE, detector_state
from resloc.cl.kernels_fusion import KERNEL_UPDATES, NAIVE_UPDATE, fusion_commit, fusion_state
from resloc.cl.kernels_gauge import gauge_commit, gauge_state, gauge_undo, no_gauge
from resloc.cl.kernels_links import OK
from resloc.cl.kernels_rounds import every_stage, rounds_warm_up_batch, run_link_loop
from resloc.cl.kernels_tamper import no_tamper
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.linalg import JITTER_LEVELS

__all__ = [
    "HAVE_NUMBA",
    "KernelLinks",
    "KernelOptions",
    "KernelOutputs",
    "KernelRobots",
    "backend",
    "fast_correct",
    "options_beyond_paper",
    "set_backend",
    "use_backend",
    "warm_up",
]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)


class KernelLinks(NamedTuple):
    """Per-link inputs, each with leading axis E (rows sorted by observer)."""

    i: np.ndarray  # (E,) int64 observers
    z: np.ndarray  # (E, 2) measured range, bearing
    x_nb: np.ndarray  # (S, 3) transmitted estimates: link e's is row nb[e]
    P_nb: np.ndarray  # (S, 3, 3)
    nb: np.ndarray  # (E,) int64 row of x_nb / P_nb (LinkBatch.neighbour_rows)
    channel_ok: np.ndarray  # (E,) bool
    last_norm: np.ndarray  # (E,) last delivered norm (``last_sent``), else (0,)
    x_ref: np.ndarray  # (E, 3) the estimate of j the moments use (cached or x_nb)
    P_ref: np.ndarray  # (E, 3, 3)
    known: np.ndarray  # (E,) bool: j's estimate received before (``cached``)


class KernelRobots(NamedTuple):
    """Per-robot inputs ``(B,)``; the gains are ``(1,)`` (scalar) or ``(B,)``."""

    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    rho: np.ndarray
    alpha: np.ndarray
    gamma: np.ndarray
    zeta_s: np.ndarray
    zeta_c: np.ndarray


class KernelOptions(NamedTuple):
    """The step's scalar options and constants."""

    R: np.ndarray  # (2, 2)
    noise_std: np.ndarray  # (2,)
    detector: bool
    trigger: bool
    detector_norm: int  # NORM_CODE
    trigger_norm: int
    risk_factor_floor: float
    last_sent: bool
    jitter: np.ndarray  # escalating Cholesky jitter levels
    cached: bool  # neighbour estimates: the last received (else the transmitted one)
    update_without_transmission: bool


class KernelOutputs(NamedTuple):
    """Per-link decisions, written by the kernel."""

    norm: np.ndarray  # (E,)
    threshold: np.ndarray  # (E,)
    flags: np.ndarray  # (5, E) bool: detected, triggered, delivered, fused, repaired


class CompiledBookkeeping(NamedTuple):
    """What a fusion method with a compiled twin records beside the kernel's update.

    Attributes
    ----------
    state : callable ``(memory, E) -> KernelGauge or None``
        (:class:`~resloc.cl.kernels_gauge.KernelGauge`)
        The kernel's working arrays for ``E`` links (None: the kernel cannot run it).
    commit : callable ``(memory, state, i, j, fused) -> None``
        Hands the kernel's records to the method's state in ``memory``.
    undo : callable ``(memory, state) -> None``
        The kernel failed: puts back what it changed in place in ``memory``.
    """

    state: Callable
    commit: Callable
    undo: Callable


def _nothing_to_commit(memory, state, i, j, fused) -> None:
    del memory, state, i, j, fused


def _nothing_to_undo(memory, state) -> None:
    del memory, state


def _gauge_commit(memory, state, i, j, fused) -> None:
    gauge_commit(memory.joint, state, i, j, fused)


def _gauge_undo(memory, state) -> None:
    gauge_undo(memory.joint, state)


#: The per-link bookkeeping of a fusion method in the compiled path, by the name its strategy
#: declares (:attr:`FusionStrategy.kernel_bookkeeping
#: <resloc.cl.fusion_methods.FusionStrategy.kernel_bookkeeping>`).
COMPILED_BOOKKEEPING: dict[str, CompiledBookkeeping] = {
    "none": CompiledBookkeeping(
        lambda memory, E: no_gauge(E), _nothing_to_commit, _nothing_to_undo
    ),
    "gauge": CompiledBookkeeping(
        lambda memory, E: None if memory is None else gauge_state(memory.joint, E),
        _gauge_commit,
        _gauge_undo,
    ),
}


#: Per structure type: the positions of its fields that are structures themselves.
_NESTED: dict[type, tuple[int, ...]] = {}


def _plain(structure: tuple) -> tuple:
    """A kernel input structure (a NamedTuple, nested ones too) as plain tuples, the form
    the compiled loop is called with: numba types a NamedTuple argument in Python, a plain
    tuple by its fast fingerprint (measured: the link loop's ten structures cost 16.5 us a
    call as NamedTuples, 7 us as plain tuples). The structures keep their NamedTuple
    classes as their documented layout; the kernels read their fields by position."""
    nested = _NESTED.get(type(structure))
    if nested is None:
        nested = _NESTED[type(structure)] = tuple(
            k for k, v in enumerate(structure) if isinstance(v, tuple)
        )
    if not nested:
        return tuple(structure)
    fields = list(structure)
    for k in nested:
        fields[k] = _plain(fields[k])
    return tuple(fields)


#: Per structure type: its fields' positions by name.
_FIELDS: dict[type, dict[str, int]] = {}


#: The last structure :func:`_plain_with` was given, its plain form, the changes' names and
#: values and the result (a run's steady state gives the same detection structure every
#: step, kernels_stores.steady_state, and the same pre-passes' arrays, kernels_prepass).
_LAST_PLAIN: list = [None, None, (), (), None]


def _plain_with(structure: tuple, changes: dict) -> tuple:
    """``_plain(structure._replace(**changes))`` without the NamedTuple built between
    (``_replace`` costs ~0.7 us and a keyword argument ~0.5 more), from the plain form of
    the last ``structure`` when it is the same object (immutable: its plain form too), the
    last result when the changes are the same objects too."""
    if not changes:
        return _plain(structure)
    last, plain, names, values, result = _LAST_PLAIN
    new_names, new_values = tuple(changes), tuple(changes.values())
    if last is structure and names == new_names:  # (the same names: as many values)
        for a, b in zip(values, new_values, strict=True):  # (all() of a generator: 0.3 us)
            if a is not b:
                break
        else:
            return result
    if last is not structure:
        plain = _plain(structure)
    index = _FIELDS.get(type(structure))
    if index is None:
        index = _FIELDS[type(structure)] = {name: k for k, name in enumerate(structure._fields)}
    fields = list(plain)
    for name, value in changes.items():
        fields[index[name]] = _plain(value) if isinstance(value, tuple) else value
    result = tuple(fields)
    _LAST_PLAIN[:] = [structure, plain, new_names, new_values, result]
    return result


def _per_robot(v) -> np.ndarray:
    """A scalar or per-robot gain as a contiguous float array of shape (1,) or (B,)."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(v, dtype=float)).ravel())


def _contiguous(a, dtype=float) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


class _Prepared(NamedTuple):
    """What a correction takes from ``params`` alone (a frozen dataclass: a run passes the
    same object every step), prepared once."""

    gains: tuple[np.ndarray, ...]  # rho, alpha, gamma, zeta_s, zeta_c: (1,) or (B,)
    options: KernelOptions
    strategy: object  # the fusion method's FusionStrategy
    problem: str | None  # why the strategy cannot run with params
    bookkeeping: CompiledBookkeeping
    last_sent: bool
    cached: bool
    plain_options: tuple  # options as the kernel is called with it (_plain)


_last_prepared: tuple = (None, None)


def _prepared(params: CLParams) -> _Prepared:
    """The gains, options and fusion strategy of ``params`` as the kernel takes them, kept
    for the last ``params`` object."""
    global _last_prepared
    ref, prepared = _last_prepared
    if ref is not None and ref() is params:
        return prepared
    gains = params.rho, params.alpha, params.gamma, params.zeta_s, params.zeta_c
    last_sent = params.threshold_innovation is ThresholdInnovation.LAST_SENT
    cached = params.neighbour_estimate is NeighbourEstimate.CACHED
    options = KernelOptions(
        _contiguous(params.R),
        _contiguous(params.noise_std),
        bool(params.detector),
        bool(params.trigger),
        NORM_CODE[params.detector_norm],
        NORM_CODE[params.trigger_norm],
        float(params.risk_factor_floor),
        last_sent,
        _JITTER,
        cached,
        bool(params.update_without_transmission),
    )
    strategy = fusion_strategy(params.fusion)
    prepared = _Prepared(
        tuple(_per_robot(g) for g in gains),
        options,
        strategy,
        strategy.problem(params),
        COMPILED_BOOKKEEPING[strategy.kernel_bookkeeping],
        last_sent,
        cached,
        _plain(options),
    )
    try:
        _last_prepared = (weakref.ref(params), prepared)
    except TypeError:  # not weakly referenceable: no cache
        _last_prepared = (None, None)
    return prepared


#: Per filter (a run's estimators alternate): the last ``params``, key and refusal.
_refusals: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _refusal(filt, params: CLParams, links: LinkBatch) -> str | None:
    """:func:`~resloc.cl.backend.kernel_refusal`, kept per filter for its last ``params``,
    backend and the links' optional fields it reads (whether there is a tamper hook and
    whether it has a compiled form, whether there are transmitted independent parts)."""
    tamper = links.tamper
    form = 0 if tamper is None else 1 + (getattr(tamper, "kernel_form", None) is None)
    key = (backend(), form, links.P_nb_ind is None, links.z_reciprocal is None)
    try:
        params_ref, last_key, refusal = _refusals[filt]
        if last_key == key and params_ref() is params:
            return refusal
    except (KeyError, TypeError):
        pass
    refusal = kernel_refusal(filt, params, links)
    try:
        _refusals[filt] = (weakref.ref(params), key, refusal)
    except TypeError:  # not hashable or weakly referenceable: no cache
        pass
    return refusal


_NO_TAMPER: list = []


def _no_tamper():
    """:func:`~resloc.cl.kernels_tamper.no_tamper`, built once (the kernel only reads it)."""
    if not _NO_TAMPER:
        _NO_TAMPER.append(no_tamper())
    return _NO_TAMPER[0]


_NO_ROWS = np.zeros(0, np.int64)


def _shape(a) -> tuple:
    """``np.shape(a)`` without its dispatch for an array (a third of a microsecond each)."""
    return a.shape if type(a) is np.ndarray else np.shape(a)


def _shapes_ok(x, P, links: LinkBatch, li, lj, robots: KernelRobots, neighbours) -> bool:
    """Every index the kernel will use is in range (the compiled loop does not check), and
    no link repeats the one before it. ``li``, ``lj``: the links' observers and observed
    nodes as contiguous int64 arrays."""
    E = len(li)
    nb, x_nb, P_nb = neighbours
    S = len(x_nb)
    if nb is not None:
        if not isinstance(nb, np.ndarray) or nb.shape != (E,) or nb.dtype.kind not in "iu":
            return False
        nb = _contiguous(nb, np.int64)
    B = observer_bound(li, lj, _NO_ROWS if nb is None else nb, S)
    x_shape, P_shape = _shape(x), _shape(P)
    if B < 1 or len(x_shape) != 2 or len(P_shape) != 3 or x_shape[0] < B or P_shape[0] < B:
        return False
    if x_shape[1] != 3 or P_shape[1:] != (3, 3):
        return False
    if _shape(x_nb) != (S, 3) or _shape(P_nb) != (S, 3, 3) or (nb is None and S != E):
        return False
    if _shape(links.z) != (E, 2) or _shape(links.channel_ok) != (E,) or _shape(links.j) != (E,):
        return False
    for a in robots[:3]:  # risks and lambda2: every observer's
        if a.ndim != 1 or len(a) < B:
            return False
    for a in robots[3:]:  # gains: one, or every observer's
        if a.shape[0] != 1 and a.shape[0] < B:
            return False
    return True


def _cached_rows(memory, li, lj, nb, x_nb, P_nb, last_sent: bool):
    """The per-link inputs of ``cached`` neighbour estimates
    (:meth:`~resloc.cl.memory.LinkMemory.cached_rows`, one compiled pass): the transmitted
    estimates per link ``(E, 3)``, ``(E, 3, 3)``, the estimates the moments use (j's last
    received where robot i has one, else the transmitted: twin ``resloc.cl.step._decide``),
    whether there is one ``(E,)`` and, with ``last_sent``, the last delivered norms
    ``(E,)`` (else ``(0,)``)."""
    rows = np.arange(len(li), dtype=np.int64) if nb is None else _contiguous(nb, np.int64)
    return memory.cached_rows(li, lj, rows, _contiguous(x_nb), _contiguous(P_nb), last_sent)


#: The options' kernel modules by name, imported on first use (:func:`_stage`).
_STAGES: dict = {}


def _stage(name: str):
    """The module ``resloc.cl.<name>`` of an option's stage, imported on the first step
    that runs it (numba then compiles its kernels on their first call) and kept: an import
    statement in :func:`fast_correct` costs ~0.5 us a step."""
    module = _STAGES.get(name)
    if module is None:
        module = _STAGES[name] = importlib.import_module("resloc.cl." + name)
    return module


def fast_correct(
    filt, x, P, links: LinkBatch, params: CLParams, memory=None, buffers=None
) -> tuple[np.ndarray, np.ndarray, LinkOutcome] | None:
    """The whole correction of :func:`~resloc.cl.step.correct` in one compiled call.

    Returns ``None`` when :func:`~resloc.cl.backend.kernel_refusal` gives a reason, when the
    input is inconsistent (the reference path then raises the explanatory error) or when a
    covariance is not positive definite (the reference path raises the library's
    :class:`NumericalError`). Nothing is modified in that case. Otherwise ``memory`` (read
    only with ``last_sent``) is updated with the delivered links, as the reference does.

    Shapes and ``buffers`` (checked by the caller) as in :func:`~resloc.cl.step.correct`;
    the outcome has ``compiled = True``.
    """
    if _refusal(filt, params, links) is not None:
        return None
    witness = None
    if params.witness:  # the notes read the claims as sent (kernels_witness)
        witness = _stage("kernels_witness").WitnessInputs.of(links)
    prepared = _prepared(params)
    # the claims, zone's readings and the pre-passes in one compiled call after the stores'
    # look-ups (kernels_prepass), where nothing runs between them
    one_pass = _stage("kernels_prepass").applies(params, links, prepared.cached)
    if params.redundancy and not one_pass:
        # The redundancy stage judges the links as reported at the predicted estimates
        # (claims capped, a tamper hook applied to every row: kernels_redundancy)
        links = _stage("kernels_redundancy").capped_links(  # compiled on first use
            filt, x, P, links, params, fusion_strategy(params.fusion), memory
        )
        if links is None:
            return None
    elif params.zone_landmarks and not params.redundancy:  # (with it: between cap and hook)
        from resloc.cl.kernels_claims import claimed_links  # compiled on first use

        links = claimed_links(params, links)
    if witness is not None:  # the readings as reported; the verdict known before the loop
        witness_stage = _stage("kernels_witness")
        strategy = fusion_strategy(params.fusion)
        links = witness_stage.witness_links(filt, x, P, links, strategy, memory, params.R)
        witness = witness_stage.witness_verdict(params, memory, x, P, links, witness)
        if witness is None:
            return None  # the reference path raises the explanatory error
    if params.reciprocal and links.tamper is not None:
        # The reciprocal check compares the readings as reported with the partners'
        # (a tamper hook applied to every row: kernels_reciprocal; params.R is a new array)
        strategy = fusion_strategy(params.fusion)  # (the prepared one, before shapes)
        links = _stage("kernels_reciprocal").partner_readings(
            filt, x, P, links, strategy, memory, params.R
        )
    zone = None
    if params.zone_trust and not one_pass:  # the partners' readings attached (kernels_zone)
        zoned = _stage("kernels_zone").zone_state(
            filt, x, P, links, params, fusion_strategy(params.fusion), memory
        )
        if zoned is None:
            return None  # the reference path raises the explanatory error
        links, zone = zoned
    last_sent, cached = prepared.last_sent, prepared.cached
    need_memory = last_sent or cached
    if need_memory and memory is None:
        return None  # the reference path raises the explanatory error
    li = _contiguous(links.i, np.int64)
    lj = _contiguous(links.j, np.int64)
    E = len(li)
    robots = KernelRobots(
        _contiguous(links.risk_s),
        _contiguous(links.risk_c),
        _contiguous(links.lambda2),
        *prepared.gains,
    )
    neighbours = links.neighbour_rows()
    if E == 0 or not _shapes_ok(x, P, links, li, lj, robots, neighbours):
        return None
    strategy = prepared.strategy
    if prepared.problem is not None:
        return None  # the reference path raises the explanatory error
    tamper = _no_tamper() if links.tamper is None else links.tamper.kernel_form
    z = links.z
    if tamper.on:  # the attacker's honest measurements and observers must be this batch's
        if tamper.z.shape != (E, 2) or not np.array_equal(tamper.observer, li):
            return None
        z = tamper.z
    bookkeeping = prepared.bookkeeping
    fusion = fusion_state(strategy.kernel_update, params.ci_criterion, memory, links, E)
    gauge = bookkeeping.state(memory, E)
    if gauge is None or fusion is None:
        return None  # the reference path raises the explanatory error, or records exactly
    detection = detector_state(params, memory, li, lj)
    if detection is None:
        return None  # the reference path raises the explanatory error
    defence = defence_state(params, memory, li)
    if defence is None:
        detection.undo()
        return None  # the reference path raises the explanatory error
    nb, x_nb, P_nb = neighbours
    if cached:  # per-link rows, j's last received estimate where there is one
        x_nb, P_nb, x_ref, P_ref, known, last = _cached_rows(
            memory, li, lj, nb, x_nb, P_nb, last_sent
        )
        nb = np.arange(E, dtype=np.int64)
    else:
        if nb is None:  # the per-link arrays themselves
            nb = np.arange(E, dtype=np.int64)
        x_nb, P_nb, nb = _contiguous(x_nb), _contiguous(P_nb), _contiguous(nb, np.int64)
        last = np.zeros(E if last_sent else 0)
        known = np.zeros(E, dtype=np.bool_)
        x_ref, P_ref = x_nb, P_nb
        if last_sent and len(memory):
            found, pos = memory.lookup(li, lj)
            last = np.where(found, memory.last_norm[pos], 0.0)
    detect = detection.kernel
    changes = {}  # the pre-passes' verdicts for the loops (KernelDetection's fields)
    fixes = None
    paired = None
    if one_pass:  # the claims, zone's readings, the pre-passes (kernels_prepass)
        passes = _stage("kernels_prepass").prepass(
            params, memory, li, lj, _contiguous(z), _contiguous(x), _contiguous(P), x_nb, P_nb,
            nb, detect,
        )  # fmt: skip
        if passes is None:
            bookkeeping.undo(memory, gauge)
            defence.undo()
            detection.undo()
            return None  # the reference path raises the explanatory error
        x_nb, P_nb, nb, zone, fixes, paired = passes
        x_ref, P_ref = x_nb, P_nb
        changes["fixes"] = fixes.discard  # (with the reciprocal check's)
        if zone is not None:
            changes["zone"] = zone.kernel
    elif params.redundancy:  # every link judged once, before the loop (kernels_redundancy)
        fixes = _stage("kernels_redundancy").redundancy_verdict(
            params, memory, li, lj, z, x, P, x_nb, P_nb, nb, detect
        )
        if fixes is None:
            bookkeeping.undo(memory, gauge)
            defence.undo()
            detection.undo()
            return None  # the reference path raises the explanatory error
        changes["fixes"] = fixes.discard
    if params.reciprocal and not one_pass:  # every link's range against its partner's
        reciprocal_verdict = _stage("kernels_reciprocal").reciprocal_verdict
        z_rec = links.z_reciprocal if zone is None else zone.kernel.z_reciprocal  # (found)
        other = None if fixes is None else fixes.discard  # (ORed into in place)
        paired = reciprocal_verdict(params, memory, li, lj, z, z_rec, x, x_nb, nb, detect, other)
        if paired is None:
            if fixes is not None:
                fixes.undo()
            bookkeeping.undo(memory, gauge)
            defence.undo()
            detection.undo()
            return None  # the reference path raises the explanatory error
        changes["fixes"] = paired.discard  # (with the redundancy pre-pass's)
    if zone is not None and not one_pass:
        changes["zone"] = zone.kernel
    if witness is not None:
        changes["witness"] = witness.discard
    detect = _plain_with(detect, changes)  # (no _replace: ~2 us with two fields)
    kernel_links = KernelLinks(
        li,
        _contiguous(z),
        x_nb,
        P_nb,
        nb,
        _contiguous(links.channel_ok, np.bool_),
        last,
        x_ref,
        P_ref,
        known,
    )
    out = KernelOutputs(np.empty(E), np.empty(E), np.zeros((5, E), dtype=np.bool_))
    if buffers is None:
        x_out = np.array(x, dtype=float, order="C", copy=True)
        P_out = np.array(P, dtype=float, order="C", copy=True)
    else:  # the caller's arrays (step.check_buffers): no state allocated per step
        x_out, P_out = buffers
        x_out[...] = x
        P_out[...] = P
    spec: FilterKernelSpec = filter_kernel_spec(filt)
    loop = run_link_loop  # the rounds where they pay (kernels_rounds), else row order
    if params.update_mode is UpdateMode.SUMMED:  # every gain from the prediction
        from resloc.cl.kernels_summed import run_summed_loop as loop  # compiled on first use
    status = loop(
        x,
        P,
        x_out,
        P_out,
        tuple(kernel_links),
        tuple(robots),
        tuple(spec),
        prepared.plain_options,
        _plain(fusion),
        detect,
        _plain(defence.kernel),
        tuple(gauge),
        _plain(tamper),
        out,
    )
    if status != OK:
        if paired is not None:
            paired.undo()
        if fixes is not None:
            fixes.undo()
        bookkeeping.undo(memory, gauge)
        defence.undo()
        detection.undo()
        return None
    if zone is not None:  # the pre-passes keep no state of the rows they did not judge
        _stage("kernels_zone").keep_unjudged_state(zone, (fixes, paired), li, lj)
    detected, triggered, delivered, fused, repaired = out.flags
    bookkeeping.commit(memory, gauge, li, lj, fused)
    fusion_commit(fusion, memory, li, fused)
    P_out = strategy.finish(memory, P_out, lj, delivered)
    if need_memory and delivered.any():
        memory.store_delivered(li, lj, delivered, x_nb, P_nb, nb, out.norm)
    if witness is not None:  # the step's notes, at its end (as the reference)
        witness.record(params, memory)
    outcome = LinkOutcome(
        out.norm, out.threshold, detected, triggered, delivered, fused, repaired, compiled=True
    )
    return x_out, P_out, outcome


def options_beyond_paper(params: CLParams) -> bool:
    """Whether corrections with ``params`` run an option's stage in the compiled loops
    (:func:`~resloc.cl.kernels_rounds.beyond_paper` on the structures ``params`` give; an
    adversary's tamper hook, which comes with the links, is the caller's to add)."""
    prepared = _prepared(params)
    strategy = prepared.strategy
    if KERNEL_UPDATES[strategy.kernel_update] != NAIVE_UPDATE:
        return True
    if strategy.kernel_bookkeeping != "none" or prepared.cached:
        return True
    if params.redundancy or params.reciprocal or params.zone_trust or params.witness:
        return True  # (the pre-passes' verdicts and zone trust's enter the options' form)
    rows = np.zeros(1, np.int64)
    detection = detector_state(params, None, rows, rows)  # None: a stage needs the memory
    defence = defence_state(params, None, rows)
    if detection is None or defence is None:
        return True
    kernel = detection.kernel
    return bool(kernel[0] or kernel[6] or defence.kernel[0] or defence.kernel[5])


def warm_up(paper: bool = True, options: bool = True) -> bool:
    """Compile (or load from the on-disk cache) the kernels outside any timed section.

    Parameters
    ----------
    paper, options : bool
        Which forms of the link loops (:func:`~resloc.cl.kernels_rounds.beyond_paper`):
        the paper's method's (without the options' stages), the options' (every stage).
        A run uses one of them (:func:`options_beyond_paper`): a fresh clone's first run
        of the paper's method does not compile the other.

    Returns
    -------
    bool
        Whether the compiled kernels are in use.
    """
    from resloc.cl.kernels_predict import fast_predict
    from resloc.filters.base import make_filter

    if backend() != "numba":
        return False
    x = np.array([[0.0, 0.0, 0.1], [1.0, 0.5, -0.2]])
    P = np.broadcast_to(0.01 * np.eye(3), (2, 3, 3)).copy()
    links = LinkBatch(
        np.array([0, 1]), np.array([1, 0]), np.array([[1.1, 0.4], [1.1, 2.9]]),
        x[[1, 0]], P[[1, 0]], np.array([True, True]), np.zeros(2), np.zeros(2), np.ones(2),
    )  # fmt: skip
    for kind in ("ckf", "ekf"):  # the prediction's robot-by-robot loop (kernels_predict)
        fast_predict(make_filter(kind), x, P, np.array([[0.1, 0.0], [0.1, 0.1]]), 0.1, CLParams())
    forms = [contextlib.nullcontext] if paper else []
    if options:
        forms.append(every_stage)
    for form in forms:
        with form():
            for kind in ("ckf", "ekf"):
                fast_correct(make_filter(kind), x, P, links, CLParams())
            fast_correct(make_filter("ckf"), *rounds_warm_up_batch(), CLParams())  # rounds
    return True
