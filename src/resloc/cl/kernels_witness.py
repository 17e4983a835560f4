"""Compiled path of the witness stage (:mod:`resloc.cl.detection_witness`).

The stage's verdict on a link ``(i, j)`` depends only on ``S_j`` as it stood before the
step (the notes of step ``t`` arrive with the broadcasts of ``t + 1``): it is known before
the link loop runs. :func:`witness_verdict` computes it once per step, with the step's notes
(the readings as reported, the claims as sent), and the compiled loops read it as a per-link
mask (:attr:`KernelDetection.witness <resloc.cl.kernels_detection.KernelDetection>`: a
discard on every row the other stages judge, zone trust's substituted rows included, as
``WitnessCheck.discard`` does). :meth:`WitnessVerdict.record` updates the statistic with the
step's notes once the loop has succeeded (:func:`~resloc.cl.detection_witness.record_witness`).

=============================  ==========================================================
function                       numpy twin
=============================  ==========================================================
:func:`witness_links`          the head of ``resloc.cl.step._correct_reference`` (an
                               adversary's hook applied to every row)
:func:`witness_verdict`        ``WitnessCheck.discard`` and ``step_notes`` (plus the
                               adversary's ``notes`` hook)
=============================  ==========================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.detection_witness import WitnessNotes, record_witness, step_notes, witness_state
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams, at_robots

__all__ = ["WITNESS_RUNS", "WitnessInputs", "WitnessVerdict", "witness_links", "witness_verdict"]

#: How often the compiled path took the stage's verdict (the tests read it).
WITNESS_RUNS = {"verdicts": 0}


class WitnessInputs(NamedTuple):
    """What the notes take from the batch as it arrives: the claims as sent ``(E, 3, 3)``
    (before any cap or landmark weakening) and an adversary's ``notes`` hook (or None)."""

    claimed: np.ndarray
    lie_notes: object

    @classmethod
    def of(cls, links: LinkBatch) -> WitnessInputs:
        return cls(links.P_nb, getattr(links.tamper, "notes", None))


class WitnessVerdict(NamedTuple):
    """The step's verdict ``discard (E,)`` bool and its ``notes`` (recorded at the end)."""

    discard: np.ndarray
    notes: WitnessNotes

    def record(self, params: CLParams, memory) -> None:
        """Update the statistic with the step's notes (after the loop succeeded)."""
        record_witness(self.notes, params, memory)


def witness_links(filt, x, P, links: LinkBatch, strategy, memory, R) -> LinkBatch:
    """``links`` with an adversary's hook applied to every row at the predicted estimates
    (the notes carry the readings as reported), as the reference does with the stage on;
    ``links`` itself without a hook."""
    from resloc.cl.kernels_reciprocal import partner_readings

    return partner_readings(filt, x, P, links, strategy, memory, R)


def witness_verdict(
    params: CLParams, memory, x: np.ndarray, P: np.ndarray, links: LinkBatch, inputs: WitnessInputs
) -> WitnessVerdict | None:
    """Every link's verdict (``S_j > h`` before the step) and the step's notes; ``x``, ``P``
    the predicted estimates, ``links`` with the readings as reported. None without a memory
    (the reference path raises the explanatory error)."""
    if memory is None:
        return None
    j = np.asarray(links.j)
    discard = np.ascontiguousarray(witness_state(memory, j) > at_robots(params.witness_h, j))
    notes = step_notes(
        links.z, x[links.i], P[links.i], links.x_nb, inputs.claimed, links.i, j, params
    )
    if inputs.lie_notes is not None:
        notes = inputs.lie_notes(notes)
    WITNESS_RUNS["verdicts"] += 1
    return WitnessVerdict(discard.astype(np.bool_, copy=False), notes)
