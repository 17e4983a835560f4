"""The fusion method as the compiled link loops take it (:class:`KernelFusion`): the code
of its update (:data:`KERNEL_UPDATES`), its constants and working copies of the state it
updates per link.

:func:`fusion_state` builds the :class:`KernelFusion` of the strategy's
:attr:`~resloc.cl.fusion_methods.FusionStrategy.kernel_update`: its code, its constants
(the CI criterion and the candidate weights as the kernels take them) and working copies
of the state it updates per link (split CI's independent parts; the cross-covariance
bookkeeping of ``tracked`` and ``factorized``, :mod:`resloc.cl.kernels_joint`);
:func:`fusion_commit` hands them back. The updates that change the link update itself are
compiled elsewhere: covariance intersection's weight (:mod:`resloc.cl.kernels_ci_weight`)
and update (:mod:`resloc.cl.kernels_ci_update`), split CI's
(:mod:`resloc.cl.kernels_split`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.fusion import CI_GRID, CICriterion
from resloc.cl.kernels_joint import (
    FACTORIZED,
    TRACKED,
    KernelJoint,
    joint_commit,
    joint_state,
    kernel_scratch,
    no_joint,
)
from resloc.cl.kernels_math import jit

__all__ = [
    "CI",
    "FACTORIZED_UPDATE",
    "KERNEL_UPDATES",
    "NAIVE_UPDATE",
    "SPLIT_CI",
    "TRACKED_UPDATE",
    "KernelFusion",
    "fusion_commit",
    "fusion_state",
    "kernel_fusion",
]

#: Codes of the link update in the kernel.
NAIVE_UPDATE = 0  # the filter's Kalman update (naive and gauge fusion)
CI = 1  # covariance intersection
SPLIT_CI = 2  # split covariance intersection
TRACKED_UPDATE = 3  # Kalman update under the tracked joint (resloc.cl.kernels_joint)
FACTORIZED_UPDATE = 4  # Kalman update under the factorized joint (resloc.cl.kernels_joint)
#: A strategy's ``kernel_update`` -> its code.
KERNEL_UPDATES = {
    "kalman": NAIVE_UPDATE,
    "ci": CI,
    "split_ci": SPLIT_CI,
    "tracked": TRACKED_UPDATE,
    "factorized": FACTORIZED_UPDATE,
}
_JOINT_CODES = {TRACKED_UPDATE: TRACKED, FACTORIZED_UPDATE: FACTORIZED}


class KernelFusion(NamedTuple):
    """The fusion method as the link loop takes it: its code, constants and the working
    copies of the state it updates per link (empty arrays when it keeps none)."""

    code: int  # a KERNEL_UPDATES code
    det: bool  # CI weight by the posterior determinant (else its trace)
    grid: np.ndarray  # (3, G) candidate CI weights w, 1 / w, 1 / (1 - w)
    joint: KernelJoint  # tracked / factorized: the cross-covariance bookkeeping
    independent: np.ndarray  # (B, 3, 3) split CI: the robots' independent parts
    P_nb_ind: np.ndarray  # (E, 3, 3) split CI: the transmitted independent parts
    work: np.ndarray  # (8, 3, 3) split CI: scratch
    costs: np.ndarray  # (G,) ci, split CI: scratch, the cost at each candidate weight


#: The candidate weights as the kernels take them, ``(3, G)``: the weights ``w``, ``1 / w``
#: and ``1 / (1 - w)`` (the same divisions as the reference's, done once, not per link).
_GRID = np.ascontiguousarray(np.stack([CI_GRID, 1.0 / CI_GRID, 1.0 / (1.0 - CI_GRID)]), dtype=float)
_NONE3 = np.zeros((0, 3, 3))


def kernel_fusion(code: int, criterion: CICriterion, E: int = 0) -> KernelFusion:
    """The kernel form of a fusion method with update ``code`` and CI ``criterion`` that
    keeps no per-link state."""
    return KernelFusion(
        int(code), CICriterion(criterion) is CICriterion.DET, _GRID, no_joint(E), _NONE3,
        _NONE3, np.zeros((8, 3, 3)), np.empty(_GRID.shape[1]),
    )  # fmt: skip


def fusion_state(update: str, criterion: CICriterion, memory, links, E: int):
    """The kernel form of the fusion method whose strategy declares ``kernel_update =
    update``, with working copies of its state in ``memory`` for the ``E`` links of
    ``links``; None when the kernel cannot reproduce the reference (then the reference
    raises its explanatory error, or records exactly)."""
    code = KERNEL_UPDATES[update]
    if code == SPLIT_CI:
        return _split_state(criterion, memory, links, E)
    if code in _JOINT_CODES:  # (built at once: kernel_fusion's then _replace cost ~1 us)
        joint = joint_state(_JOINT_CODES[code], memory, links.i, links.j)
        if joint is None:
            return None
        if criterion is not CICriterion.TRACE and criterion is not CICriterion.DET:
            criterion = CICriterion(criterion)
        scratch = kernel_scratch(memory.joint)  # (the joint's: no allocation a step)
        return KernelFusion(
            code, criterion is CICriterion.DET, _GRID, joint, _NONE3, _NONE3, scratch[2],
            scratch[3],
        )  # fmt: skip
    return kernel_fusion(code, criterion, E)


def _split_state(criterion: CICriterion, memory, links, E: int) -> KernelFusion | None:
    """:func:`fusion_state` of split CI: a working copy of ``memory.independent`` and the
    transmitted parts; None when a shape does not fit (the kernel does not check indices).
    Built at once, not as :func:`kernel_fusion`'s then ``_replace``; the copy and the
    observers' bound in one compiled call (:func:`_split_working_copy`), the criterion
    compared, not converted, when it is already a :class:`CICriterion` (measured,
    ``timeit``, 17 robots: 6.0 -> 2.7 -> ~1.3 us a step)."""
    independent = None if memory is None else memory.independent
    P_nb_ind = links.P_nb_ind
    if independent is None or P_nb_ind is None:
        return None
    if type(independent) is not np.ndarray or independent.dtype != _FLOAT:
        independent = np.array(independent, dtype=float)  # (the run's own is float64)
    if independent.shape[1:] != (3, 3) or np.shape(P_nb_ind) != (E, 3, 3):
        return None
    working = _split_working_copy(independent, np.asarray(links.i))
    if working.shape[0] == 0:  # an observer outside memory.independent
        return None
    if criterion is not CICriterion.TRACE and criterion is not CICriterion.DET:
        criterion = CICriterion(criterion)
    return KernelFusion(
        SPLIT_CI, criterion is CICriterion.DET, _GRID, no_joint(E), working,
        np.ascontiguousarray(P_nb_ind, dtype=float), np.zeros((8, 3, 3)),
        np.empty(_GRID.shape[1]),
    )  # fmt: skip


_FLOAT = np.dtype(float)


@jit
def _split_working_copy(independent, i):
    """A C-contiguous copy of ``independent: (B, 3, 3)`` when every observer ``i: (E,)`` is
    below ``B``, else an empty ``(0, 3, 3)`` array (the working copy of
    :func:`_split_state`; ``i``'s negative entries are refused before, by the link loop's
    checks)."""
    B = independent.shape[0]
    for e in range(i.shape[0]):
        if i[e] >= B:
            return np.empty((0, 3, 3))
    out = np.empty((B, 3, 3))
    out[:, :, :] = independent
    return out


def fusion_commit(fusion: KernelFusion, memory, i: np.ndarray, fused: np.ndarray) -> None:
    """Hand the kernel's records of a correction to the method's state in ``memory``
    (``i``: the links' observers, (E,) int64, ``fused``: (E,) bool, the kernel's own)."""
    code = fusion[0]  # (by position: a NamedTuple's field by name is a property call)
    if code == SPLIT_CI:
        memory.independent = fusion.independent
    elif code in _JOINT_CODES:
        joint_commit(fusion[3], memory, i, fused)
