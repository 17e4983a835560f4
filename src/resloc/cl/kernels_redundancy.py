"""Compiled path of the redundancy stage and its sequence test: the CL step's glue.

The redundancy stage (:mod:`resloc.cl.detection_redundancy`) and the sequence test on its
residuals (:mod:`resloc.cl.detection_sequence`) judge every link of a step once, at the
predicted estimates, before any update: their verdict does not depend on the order in which
the links are fused. The compiled correction therefore runs them as a pre-pass,
:func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`, one call over every
observer's rows, which gives the link loops (:mod:`resloc.cl.kernels_links`,
:mod:`resloc.cl.kernels_rounds`) one flag per link
(:attr:`KernelDetection.fixes <resloc.cl.kernels_detection.KernelDetection>`): discard.
The sequence test's per-link state is the same store of the run's
:class:`~resloc.cl.memory.LinkMemory` the numpy stage reads and writes
(``stage_statistic("redundancy_sequence", width=6)``), updated in place; a run can switch
paths between steps. :meth:`~resloc.cl.kernels_detection.PrepassVerdict.undo` puts it back
when the kernel gives up on a step.

=============================  ==========================================================
function                       numpy twin
=============================  ==========================================================
:func:`capped_links`           the head of ``resloc.cl.step._correct_reference`` (the
                               claims capped and weakened, an adversary's hook applied)
:func:`redundancy_verdict`     :func:`~resloc.cl.detection_redundancy.fix_evidence` and the
                               stages' ``discard`` (one step's pre-pass)
=============================  ==========================================================

The kernels live in :mod:`resloc.cl.kernels_redundancy_fixes` (the claims' factors and the
links' position fixes) and :mod:`resloc.cl.kernels_redundancy_verdicts` (fault exclusion,
the sequence test, :func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`). They are
compiled (or loaded from numba's cache) on the first step that switches the stage on: a run
without it does not pay for them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.detection_sequence import WIDTH, RedundancySequence
from resloc.cl.kernels_claims import claimed_links
from resloc.cl.kernels_detection import DetectorState, PrepassVerdict, shared_slots, store_slots
from resloc.cl.kernels_math import gain_array, per_params
from resloc.cl.kernels_reciprocal import partner_readings
from resloc.cl.kernels_redundancy_verdicts import fix_verdicts
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "FixOptions",
    "capped_links",
    "named_fix_options",
    "redundancy_verdict",
]


class FixOptions(NamedTuple):
    """The stages' options as :func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`
    takes them; gains ``(1,)`` or ``(B,)``."""

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
    argument in Python, a plain tuple by its fast fingerprint: ``kernels_plain.plain``)."""
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


_NO_STATE = np.zeros((0, WIDTH))
_NO_SLOTS = np.zeros(0, np.int64)


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
        links = claimed_links(params, links)
        if links is None:
            return None
    if links.tamper is not None:  # (with the hook's ``reported`` partner readings)
        links = partner_readings(filt, x, P, links, strategy, memory, params.R)
    return links


def redundancy_verdict(
    params, memory, li, lj, z, x, P, x_nb, P_nb, nb, detection
) -> PrepassVerdict | None:
    """The pre-pass of one step (:func:`~resloc.cl.kernels_redundancy_verdicts.fix_verdicts`):
    ``li``, ``lj`` int64 ``(E,)``, ``z: (E, 2)`` the readings as reported, ``x``, ``P``
    the predicted estimates, ``x_nb``, ``P_nb`` the claimed estimates at rows ``nb``
    (contiguous); ``detection``: the step's
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
