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
:mod:`resloc.cl.kernels_ci_weight`, :mod:`resloc.cl.kernels_ci_update`,
:mod:`resloc.cl.kernels_zone`, :mod:`resloc.cl.kernels_zone_verdicts` and, imported only
when their stages are on,
:mod:`resloc.cl.kernels_redundancy`, :mod:`resloc.cl.kernels_reciprocal`,
:mod:`resloc.cl.kernels_prepass`).

What the kernel covers is decided by :func:`resloc.cl.backend.kernel_refusal` from the
strategies; the inputs are named structures (:class:`~resloc.cl.kernels_inputs.KernelLinks`,
:class:`~resloc.cl.kernels_inputs.KernelRobots`,
:class:`~resloc.cl.kernels_inputs.KernelOptions`,
:class:`~resloc.cl.backend.FilterKernelSpec`,
:class:`~resloc.cl.kernels_detection.KernelDetection`,
:class:`~resloc.cl.kernels_inputs.KernelOutputs`). The detector stages that keep per-link
state (the CUSUMs) are in :mod:`resloc.cl.kernels_detection`.

The dispatch's parts, one job a module: the structures and the checks of their indices
(:mod:`resloc.cl.kernels_inputs`), what ``params`` alone give and the refusal, kept per
``params`` and per filter (:mod:`resloc.cl.kernels_prepared`), the plain tuples the loops
are called with (:mod:`resloc.cl.kernels_plain`), a fusion method's records beside the
update (:mod:`resloc.cl.kernels_bookkeeping`). This module makes the call and warms the
kernels up.
"""

from __future__ import annotations

import contextlib
import importlib

import numpy as np

from resloc.cl.backend import (  # backend choice re-exported for callers of this module
    HAVE_NUMBA,
    FilterKernelSpec,
    backend,
    filter_kernel_spec,
    set_backend,
    use_backend,
)
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_defence import defence_state
from resloc.cl.kernels_detection import detector_state
from resloc.cl.kernels_fusion import KERNEL_UPDATES, NAIVE_UPDATE, fusion_commit, fusion_state
from resloc.cl.kernels_inputs import (
    KernelLinks,
    KernelOutputs,
    KernelRobots,
    cached_rows,
    pair_warm_up_batch,
    shapes_ok,
)
from resloc.cl.kernels_links import OK
from resloc.cl.kernels_plain import contiguous, plain, plain_with
from resloc.cl.kernels_prepared import prepared_for, refusal
from resloc.cl.kernels_rounds import every_stage, rounds_warm_up_batch, run_link_loop
from resloc.cl.kernels_tamper import no_tamper
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.params import CLParams, UpdateMode

__all__ = [
    "HAVE_NUMBA",
    "backend",
    "fast_correct",
    "options_beyond_paper",
    "set_backend",
    "use_backend",
    "warm_up",
]

_NO_TAMPER: list = []


def _no_tamper():
    """:func:`~resloc.cl.kernels_tamper.no_tamper`, built once (the kernel only reads it)."""
    if not _NO_TAMPER:
        _NO_TAMPER.append(no_tamper())
    return _NO_TAMPER[0]


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
    if refusal(filt, params, links) is not None:
        return None
    witness = None
    if params.witness:  # the notes read the claims as sent (kernels_witness)
        witness = _stage("kernels_witness").WitnessInputs.of(links)
    prepared = prepared_for(params)
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
    li = contiguous(links.i, np.int64)
    lj = contiguous(links.j, np.int64)
    E = len(li)
    robots = KernelRobots(
        contiguous(links.risk_s),
        contiguous(links.risk_c),
        contiguous(links.lambda2),
        *prepared.gains,
    )
    neighbours = links.neighbour_rows()
    if E == 0 or not shapes_ok(x, P, links, li, lj, robots, neighbours):
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
        x_nb, P_nb, x_ref, P_ref, known, last = cached_rows(
            memory, li, lj, nb, x_nb, P_nb, last_sent
        )
        nb = np.arange(E, dtype=np.int64)
    else:
        if nb is None:  # the per-link arrays themselves
            nb = np.arange(E, dtype=np.int64)
        x_nb, P_nb, nb = contiguous(x_nb), contiguous(P_nb), contiguous(nb, np.int64)
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
            params, memory, li, lj, contiguous(z), contiguous(x), contiguous(P), x_nb, P_nb,
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
    detect = plain_with(detect, changes, memory)  # (no _replace: ~2 us with two fields)
    kernel_links = KernelLinks(
        li,
        contiguous(z),
        x_nb,
        P_nb,
        nb,
        contiguous(links.channel_ok, np.bool_),
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
        plain(fusion),
        detect,
        plain(defence.kernel),
        tuple(gauge),
        plain(tamper),
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
    prepared = prepared_for(params)
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
    x, P, links = pair_warm_up_batch()
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
