"""The attacker's copy of the victim's detector: which falsified measurements it accepts.

Every attacker of the suite knows the defence it faces completely: the victim's parameters
(:class:`~resloc.cl.params.CLParams`), its predicted measurements and innovation
covariances, and the state of every sequence test (the victim's
:class:`~resloc.cl.memory.LinkMemory`). :func:`largest_accepted` runs the victim's own
detector (:func:`resloc.cl.detection.detect`, whatever stages the defence switches on,
including stages added later) on a throw-away copy of that state, so no attacker re-derives a
test and none is limited to a margin of a threshold: it uses the whole acceptance region.
"""

from __future__ import annotations

import copy

import numpy as np

from resloc.cl.detection import DETECTOR_STAGES, Evidence, detect
from resloc.cl.detector import innovation_norm
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.filters.update import innovation

__all__ = ["accepted", "largest_accepted", "scratch_memory"]

#: Grid points of each pass; two passes resolve the accepted fraction to ``1 / 32^2``.
GRID = 33
PASSES = 2


def _scratch(value):
    if isinstance(value, np.ndarray):
        return value.copy()
    try:
        fields = vars(value)
    except TypeError:  # no attributes: a scalar, a tuple, None
        return copy.copy(value)
    out = copy.copy(value)
    for name, inner in fields.items():
        if isinstance(inner, np.ndarray):
            setattr(out, name, inner.copy())
    return out


def scratch_memory(memory: LinkMemory | None) -> LinkMemory | None:
    """A copy of the victim's memory the detector may update: arrays and the arrays of
    its per-link statistics copied (fusion bookkeeping shared: no detector stage touches
    it, and copying it would cost O(N^2))."""
    if memory is None:
        return None
    out = copy.copy(memory)
    for name, value in vars(memory).items():
        if name != "joint":
            setattr(out, name, _scratch(value))
    return out


def accepted(
    z: np.ndarray,
    z_hat: np.ndarray,
    S: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    gate_only: bool = False,
) -> np.ndarray:
    """Whether the victim's detector, in its current state, accepts measurements ``z``.

    Rows are judged as one round of the victim's correction (the per-link tests see their
    own link's state only; a row may repeat a link: each copy is judged against the state
    before this round).

    Parameters
    ----------
    z, z_hat : ndarray, shape (E, 2)
        Candidate and predicted measurements.
    S : ndarray, shape (E, 2, 2)
    i, j : ndarray of int, shape (E,)
    params : CLParams
    memory : LinkMemory or None
        The victim's memory (not modified).
    gate_only : bool
        Judge by the per-measurement gate alone (an attacker that knows nothing else).

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    nu = innovation(z, z_hat)
    norm = innovation_norm(nu, S, params.detector_norm, params.noise_std)
    evidence = Evidence(nu, S, norm, i, j, np.zeros(len(z), bool))
    if gate_only:
        gate = DETECTOR_STAGES[0]
        return ~gate.discard(evidence, params, None) if gate.active(params) else ~evidence.gated
    return ~detect(evidence, params, scratch_memory(memory))


def largest_accepted(
    z: np.ndarray,
    lie: np.ndarray,
    z_hat: np.ndarray,
    S: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    gate_only: bool = False,
) -> np.ndarray:
    """Largest ``a`` in ``[0, 1]`` per row with ``z + a lie`` accepted by the victim.

    A grid over ``[0, 1]`` (one stacked detector call) finds the largest accepted grid
    point; a second grid between it and the next point refines it. Where no point is
    accepted (the honest measurement itself fails and so does every lie along ``lie``) the
    result is 0: the measurement is discarded whatever is sent.

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Honest measurements.
    lie : ndarray, shape (E, 2)
        The full injection per row.
    z_hat, S, i, j, params, memory, gate_only
        As :func:`accepted`.

    Returns
    -------
    ndarray, shape (E,)
    """
    E = len(z)
    if E == 0:
        return np.zeros(0)
    lo = np.zeros(E)
    width = np.ones(E)
    any_ok = np.zeros(E, bool)
    for _ in range(PASSES):
        frac = lo[None] + np.linspace(0.0, 1.0, GRID)[:, None] * width[None]  # (GRID, E)
        cand = z[None] + frac[..., None] * lie[None]
        ok = accepted(
            cand.reshape(-1, 2),
            np.tile(z_hat, (GRID, 1)),
            np.tile(S, (GRID, 1, 1)),
            np.tile(i, GRID),
            np.tile(j, GRID),
            params,
            memory,
            gate_only,
        ).reshape(GRID, E)
        found = ok.any(axis=0)
        best = GRID - 1 - np.argmax(ok[::-1], axis=0)
        lo = np.where(found, frac[best, np.arange(E)], lo)
        any_ok |= found
        width = width / (GRID - 1)
    return np.where(any_ok, np.minimum(lo, 1.0), 0.0)
