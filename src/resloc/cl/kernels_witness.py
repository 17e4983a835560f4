"""Compiled path of the witness stage (:mod:`resloc.cl.detection_witness`): the CL step's
glue.

Receiver i's verdict on a link ``(i, j)`` depends only on ``S_{i,j}`` after the notes of
the step before arrived with this step's frames
(:func:`~resloc.cl.detection_witness_frames.delivered_store`): it is known before the link
loop runs. :func:`witness_verdict` computes it once per step, with the step's notes (the
readings as reported, the claims as sent), and the compiled loops read it as a per-link
mask (:attr:`KernelDetection.witness <resloc.cl.kernels_detection.KernelDetection>`: a
discard on every row the other stages judge, zone trust's substituted rows included, as
``WitnessCheck.discard`` does). :meth:`WitnessVerdict.record` puts the delivered statistic
and the step's notes in the memory once the loop has succeeded (nothing to undo before).

=============================  ==========================================================
function                       numpy twin
=============================  ==========================================================
:class:`WitnessInputs`         the claims as sent and the adversary's ``notes`` hook, as
                               ``resloc.cl.step._correct_reference`` keeps them
:func:`witness_links`          the head of ``resloc.cl.step._correct_reference`` (an
                               adversary's hook applied to every row)
:func:`witness_verdict`        ``deliver_witness``, ``WitnessCheck.discard`` and
                               ``step_notes`` (plus the adversary's ``notes`` hook)
=============================  ==========================================================

The compiled pieces live in their own modules: the notes
(:mod:`resloc.cl.kernels_witness_notes`), the statistic of groups of notes and its
enumeration of their sets (:mod:`resloc.cl.kernels_witness_statistic`), the receivers'
delivery (:mod:`resloc.cl.kernels_witness_frames`) and the record of the notes
(:mod:`resloc.cl.kernels_witness_pending`). In the CL
step, :func:`witness_verdict` runs the delivery, the verdict, the step's notes and their
record in one compiled call (:mod:`resloc.cl.kernels_witness_step`), the separate calls
when that one declines. :data:`WITNESS_RUNS` counts what every one of them ran.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.detection_witness import WitnessNotes, step_notes
from resloc.cl.detection_witness_frames import (
    PENDING,
    PENDING_WIDTH,
    delivered_store,
    put_store,
    record_witness,
)
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkStatistic
from resloc.cl.params import CLParams, at_robots

__all__ = [
    "WITNESS_RUNS",
    "WitnessInputs",
    "WitnessVerdict",
    "witness_links",
    "witness_verdict",
]

#: How often the compiled path took the stage's verdict, computed notes, statistics, the
#: receivers' delivered statistic (:mod:`resloc.cl.kernels_witness_frames`) and how many
#: distinct sets of notes that pass enumerated, the notes recorded in place
#: (:mod:`resloc.cl.kernels_witness_pending`), the whole
#: step in one call (:mod:`resloc.cl.kernels_witness_step`; the tests read it).
WITNESS_RUNS = {
    "verdicts": 0,
    "notes": 0,
    "statistics": 0,
    "delivered": 0,
    "enumerated": 0,
    "records": 0,
    "steps": 0,
}


class WitnessInputs(NamedTuple):
    """What the notes take from the batch as it arrives: the claims as sent (before any
    cap or landmark weakening), link ``e``'s at ``claims[rows[e]]`` (``rows`` None: the
    per-link array itself; :meth:`LinkBatch.neighbour_rows`, no copy), and an adversary's
    ``notes`` hook (or None)."""

    rows: np.ndarray | None
    claims: np.ndarray
    lie_notes: object

    @classmethod
    def of(cls, links: LinkBatch) -> WitnessInputs:
        rows, _, claims = links.neighbour_rows()
        return cls(rows, claims, getattr(links.tamper, "notes", None))

    @property
    def claimed(self) -> np.ndarray:
        """The claims per link ``(E, 3, 3)``."""
        return self.claims if self.rows is None else self.claims[self.rows]


class WitnessVerdict(NamedTuple):
    """The step's verdict ``discard (E,)`` bool, the receivers' statistic after the notes
    that arrived with this step's frames (``store``) and the step's ``notes``: both put in
    the memory once the loop has succeeded. ``pending``: the pending store's values with
    the notes already recorded (:mod:`resloc.cl.kernels_witness_step`; ``notes`` then
    None), or None."""

    discard: np.ndarray
    store: LinkStatistic
    notes: WitnessNotes | None
    pending: np.ndarray | None = None

    def record(self, params: CLParams, memory) -> None:
        """The delivered statistic and the step's notes into ``memory`` (after the loop)."""
        put_store(memory, self.store)
        if self.pending is None:
            record_witness(self.notes, params, memory)
            return
        memory.stage_statistic(PENDING, width=PENDING_WIDTH).values = self.pending
        WITNESS_RUNS["records"] += 1


def witness_links(filt, x, P, links: LinkBatch, strategy, memory, R) -> LinkBatch:
    """``links`` with an adversary's hook applied to every row at the predicted estimates
    (the notes carry the readings as reported), as the reference does with the stage on;
    ``links`` itself without a hook."""
    if links.tamper is None:  # (partner_readings' own first test, without its import)
        return links
    from resloc.cl.kernels_reciprocal import partner_readings

    return partner_readings(filt, x, P, links, strategy, memory, R)


#: :func:`~resloc.cl.kernels_witness_step.fused_verdict`, once imported.
_FUSED: list = []


def witness_verdict(
    params: CLParams, memory, x: np.ndarray, P: np.ndarray, links: LinkBatch, inputs: WitnessInputs
) -> WitnessVerdict | None:
    """Every link's verdict (``S_{i,j} > h`` after the notes that arrived with this step's
    frames: :func:`~resloc.cl.detection_witness_frames.delivered_store`) and the step's
    notes; ``x``, ``P`` the predicted estimates, ``links`` with the readings as reported.
    None without a memory (the reference path raises the explanatory error)."""
    if memory is None:
        return None
    if not _FUSED:  # (kernels_witness_step imports this module: imported on first use)
        from resloc.cl.kernels_witness_step import fused_verdict

        _FUSED.append(fused_verdict)
    fused = _FUSED[0](params, memory, x, P, links, inputs)
    if fused is not None:
        return fused
    j = np.asarray(links.j)
    store = delivered_store(params, memory, links.i, j, links.channel_ok)
    discard = np.ascontiguousarray(store.get(links.i, j) > at_robots(params.witness_h, j))
    notes = step_notes(
        links.z,
        x[links.i],
        P[links.i],
        links.x_nb,
        inputs.claimed,
        links.i,
        j,
        params,
        links.channel_ok,
    )
    if inputs.lie_notes is not None:
        notes = inputs.lie_notes(notes)
    WITNESS_RUNS["verdicts"] += 1
    return WitnessVerdict(discard.astype(np.bool_, copy=False), store, notes)
