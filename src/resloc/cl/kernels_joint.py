"""Compiled twins of the cross-covariance methods: ``tracked`` and ``factorized`` fusion.

Both fuse with the moments of ``z_ij`` under a correlated joint ``[[P_i, C_ij], [C_ij^T,
P_j]]`` (:func:`resloc.cl.tracking.joint_moments`: the filter's points drawn from the 6 x 6
Cholesky factor, or the EKF's linearization) and the Kalman update ``P - K S K^T``; they
differ in where ``C_ij`` comes from and what an update records:

``tracked`` (:class:`~resloc.cl.tracking.JointCovariance`)
    Robot i's current error is ``M_i e_pred + w_i``. Within one correction ``M_i`` has a
    block at i's own column (``A_i``, the product of its ``I - K H_i``) and one per link it
    fused (``B_ij = -K H_j`` left-multiplied by its later gains): the kernel keeps those
    blocks (:class:`KernelJoint` ``A``, ``Bij``), the propagated noise and each robot's
    rows of ``M Sigma`` (``rows``, updated by every record: ``M_i Sigma <- G M_i Sigma +
    B_ij Sigma[j]``), whose block at j is ``C_ij = M_i Sigma[:, j]``. The
    covariance a robot keeps after an update, ``P_i = M_i Sigma M_i^T + N_i`` in the
    reference, is the same quantity by the update's recursion
    ``[G, -K H_j] [[P_i, C_ij], [C_ij^T, P_j]] [G, -K H_j]^T + K R K^T`` (``Sigma_ii`` at
    the robot's first link). The records keep each fused link's gain ``G`` (``gains``) and
    leave its products with the robot's earlier ``B_ij`` to the commit. :func:`joint_commit`
    applies them, hands ``M`` to the joint by its blocks and computes the end of step
    (``Sigma <- M Sigma M^T + N``) from them and the rows
    (:mod:`resloc.cl.kernels_tracked_step`).
``factorized`` (:class:`~resloc.cl.factorized.FactorizedCovariance`)
    ``C_ij = sigma_ij sigma_ji,pred^T`` shrunk to a valid joint
    (:func:`~resloc.cl.factorized.valid_cross`); an update left-multiplies every factor
    robot i holds, its ``A_i`` and ``B_i.`` by ``G = I - K H_i`` and records ``B_ij -= K
    H_j``. The kernel multiplies only ``A_i`` per link: a factor robot i holds is then
    ``A_i sigma_il`` (``sigma_il`` as the step began), formed where a link reads it, and
    :func:`joint_commit` applies the products once (the factors by ``A_i``, each ``B_ij``
    by the gains of i's later links), not ``N`` matrix products per update, and closes
    the end-of-step pairs in the same pass (:mod:`resloc.cl.kernels_factorized_step`).

The per-link pieces are in :mod:`resloc.cl.kernels_joint_links` and
:mod:`resloc.cl.kernels_joint_records` (``joint_record``), their rounds in
:mod:`resloc.cl.kernels_joint_rounds`; this module holds the state the link loops work on
and its hand-over to the numpy bookkeeping.

====================================================  ===================================
kernel function (``resloc.cl.kernels_joint_links``)   numpy twin
====================================================  ===================================
:func:`joint_commit` (this module)                    the state ``JointCovariance.update``
                                                      / ``FactorizedCovariance.update``
                                                      leave
``joint_cross``                                       ``JointCovariance.current`` /
                                                      ``cross`` / ``_block``;
                                                      ``FactorizedCovariance.cross``,
                                                      :func:`~resloc.cl.factorized.valid_cross`
``correlated_offsets``                                :func:`resloc.cl.tracking.joint_moments`
                                                      (points)
``correlated_linearized_moments``                     :func:`resloc.cl.tracking.joint_moments`
                                                      (EKF)
``joint_record`` (``kernels_joint_records``)           ``JointCovariance.update`` /
                                                      ``FactorizedCovariance.update`` (with
                                                      :func:`~resloc.cl.tracking.update_map`)
====================================================  ===================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.factorized import FactorizedCovariance
from resloc.cl.fusion import CI_GRID
from resloc.cl.kernels_factorized_step import commit_factorized
from resloc.cl.kernels_joint_links import FACTORIZED, NO_JOINT, TRACKED
from resloc.cl.kernels_math import jit
from resloc.cl.kernels_tracked_step import commit_tracked, take_spare_rows
from resloc.cl.tracking import JointCovariance

__all__ = [
    "FACTORIZED",
    "NO_JOINT",
    "TRACKED",
    "KernelJoint",
    "joint_commit",
    "joint_state",
    "kernel_scratch",
    "no_joint",
    "warm_up_joint_form",
]


class KernelJoint(NamedTuple):
    """A cross-covariance method's state as the link loop takes it (working copies; empty
    arrays for the arrays a method does not use)."""

    code: int  # NO_JOINT, TRACKED or FACTORIZED
    N: int  # team size (robot b is b % N of team b // N)
    nbr: np.ndarray  # (E,) int64 the links' neighbours j (batch indices)
    sigma: np.ndarray  # (T, 3N, 3N) tracked: the joint at the start of the correction
    noise: np.ndarray  # (B, 3, 3) tracked: each robot's propagated measurement noise
    A: np.ndarray  # (B, 3, 3) product of each robot's I - K H_i
    Bij: np.ndarray  # (E, 3, 3) tracked: per fused link, -K H_j times i's later gains
    sig: np.ndarray  # (B, N, 3, 3) factorized: the factors sigma_il
    sig_pred: np.ndarray  # (B, N, 3, 3) factorized: the factors the messages carry
    Bm: np.ndarray  # (B, N, 3, 3) factorized: B_il of the step
    fused: np.ndarray  # (B, N) bool factorized: i fused l's estimate this step
    work: np.ndarray  # (5, 3, 3) P_i, C_ij, P_j of the moments, scratch, tracked P_i now
    J6: np.ndarray  # (2, 6, 6) scratch: the joint and its Cholesky factor
    gains: np.ndarray  # (E, 3, 3) each fused link's G = I - K H_i
    rows: np.ndarray  # (B, 3, 3N) tracked: each robot's M_i Sigma (its rows of M Sigma)


_EMPTY3 = np.zeros((0, 3, 3))
_EMPTY4 = np.zeros((0, 0, 3, 3))


_NO_JOINT = KernelJoint(
    NO_JOINT, 1, np.zeros(0, np.int64), np.zeros((0, 0, 0)), _EMPTY3, _EMPTY3, _EMPTY3,
    _EMPTY4, _EMPTY4, _EMPTY4, np.zeros((0, 0), np.bool_), np.zeros((5, 3, 3)),
    np.zeros((2, 6, 6)), _EMPTY3, _EMPTY3,
)  # fmt: skip


def no_joint(E: int) -> KernelJoint:
    """Nothing to track (every method but ``tracked`` and ``factorized``; the kernel reads
    none of its arrays)."""
    del E
    return _NO_JOINT


def joint_state(code: int, memory, i: np.ndarray, j: np.ndarray) -> KernelJoint | None:
    """The kernel's working copies of the method's state in ``memory.joint`` for the links
    ``(i, j)`` (batch indices, shapes (E,)); None when the kernel cannot reproduce the
    reference (no bookkeeping, a robot's ``local`` factors, links across teams, or updates
    already recorded by an earlier correction of the step)."""
    joint = None if memory is None else memory.joint
    nbr = np.ascontiguousarray(j, dtype=np.int64)
    E = len(nbr)
    if code == TRACKED:
        if not isinstance(joint, JointCovariance) or joint.updates:
            return None
        B = joint.T * joint.N
        recorded = _NO_JOINT.fused
    elif code == FACTORIZED:
        if not isinstance(joint, FactorizedCovariance) or joint.local:
            return None
        B = joint.B
        recorded = np.ascontiguousarray(joint.fused, dtype=np.bool_)
    else:
        return _NO_JOINT
    N = joint.N
    work, J6 = kernel_scratch(joint)[:2]
    if code == TRACKED:
        # A (identity), the noise (zero), Bij and the gains in one allocation, A and the
        # noise set by the links' check (four allocations and the identity's copy were
        # ~1.1 us a step at 17 robots and 260 links; the blocks are views of it)
        start = np.empty((2 * B + 2 * E, 3, 3))
        if not _links_within_teams(np.ascontiguousarray(i, dtype=np.int64), nbr, B, N,
                                   recorded, start, 2 * B):  # fmt: skip
            return None  # an index out of range or a link across teams
        sigma = np.ascontiguousarray(joint.sigma, dtype=float)
        rows = take_spare_rows(joint, sigma)  # M = I: each robot's rows of Sigma
        # (Bij and the gains not zeroed: every reader of tracked's takes the fused links'
        # blocks only, which the records write first)
        return KernelJoint(
            code, N, nbr, sigma, start[B : 2 * B], start[:B], start[2 * B : 2 * B + E],
            _EMPTY4, _EMPTY4, _EMPTY4, _NO_JOINT.fused, work, J6, start[2 * B + E :], rows,
        )  # fmt: skip
    A = np.empty((B, 3, 3))  # no update recorded yet: each A_i = I, B_il = 0
    if not _links_within_teams(np.ascontiguousarray(i, dtype=np.int64), nbr, B, N, recorded,
                               A, B):  # fmt: skip
        return None  # an index out of range, a link across teams, or factorized's records
    # factorized: the kernel reads the factors as the step began (never writes them)
    return KernelJoint(
        code, N, nbr, _NO_JOINT.sigma, _EMPTY3, A, np.zeros((E, 3, 3)),
        np.ascontiguousarray(joint.sig, dtype=float),
        np.ascontiguousarray(joint.sig_pred, dtype=float), np.zeros((B, N, 3, 3)),
        np.zeros((B, N), dtype=np.bool_), work, J6, np.zeros((E, 3, 3)), _EMPTY3,
    )  # fmt: skip


def kernel_scratch(joint) -> tuple:
    """The compiled corrections' scratch for ``joint``'s steps, kept on it (the run's own
    object, so it goes with its memory): ``work`` (5, 3, 3) and ``J6`` (2, 6, 6) of
    :class:`KernelJoint`, and the fusion's ``work`` (8, 3, 3) and ``costs`` (G,)
    (:class:`~resloc.cl.kernels_fusion.KernelFusion`, which only ``ci`` and ``split_ci``
    read). Each is written before it is read within a link, so one set serves every step;
    four allocations a step fewer (~0.7 us, ``fusion_state`` of a 17-robot step)."""
    kept = getattr(joint, "compiled_scratch", None)
    if kept is None:
        kept = (np.zeros((5, 3, 3)), np.zeros((2, 6, 6)), np.zeros((8, 3, 3)),
                np.empty(len(CI_GRID)))  # fmt: skip
        joint.compiled_scratch = kept
    return kept


@jit
def _links_within_teams(i, nbr, B, N, recorded, start, zero_to):
    """Every link's observer and neighbour in ``[0, B)`` and in the same team of ``N``, and
    no update recorded in ``recorded`` (factorized's pairs that fused, (B, N) bool; (0, 0)
    for none): one compiled call, ``recorded.any()`` in numpy alone cost ~0.8 us. Sets the
    step's start in ``start`` (K, 3, 3), whatever the verdict: its first ``B`` blocks the
    identity (each ``A_b``), the next up to ``zero_to`` zero (``tracked``'s noise). With
    one team (``B <= N``) every index in range is in it: no integer division per link
    (measured at 260 links: 1.0 -> 0.27 us a call, the call itself 0.22)."""
    for b in range(zero_to):
        for p in range(3):
            for q in range(3):
                start[b, p, q] = 1.0 if b < B and p == q else 0.0
    one_team = B <= N
    for e in range(i.shape[0]):
        if not (0 <= i[e] < B and 0 <= nbr[e] < B):
            return False
        if not one_team and i[e] // N != nbr[e] // N:
            return False
    flat = recorded.reshape(recorded.size)
    for k in range(flat.shape[0]):
        if flat[k]:
            return False
    return True


def joint_commit(state: KernelJoint, memory, i: np.ndarray, fused: np.ndarray) -> None:
    """Hand the kernel's records to ``memory.joint`` as the reference leaves them before its
    ``finish``: ``tracked``, ``M`` by its blocks (each robot's ``A_i`` at its own column and
    its fused links' ``B_ij`` at theirs) and the noise, and the end of step computed from
    them (:func:`~resloc.cl.kernels_tracked_step.commit_tracked`); ``factorized``, ``A``,
    ``B`` and the pairs that fused, and the factors as its ``finish`` then leaves them
    (:func:`~resloc.cl.kernels_factorized_step.commit_factorized`)."""
    code = state[0]  # (by position: a NamedTuple's field by name is a property call)
    if code == TRACKED:
        # M by its blocks (dense where the reference reads it) and the end of step computed
        # from them, while the rows are in the cache (resloc.cl.kernels_tracked_step); i and
        # fused as given (the CL kernel's own, int64 and bool, contiguous: no conversion)
        commit_tracked(state, memory.joint, i, fused)
    elif code == FACTORIZED:  # and the end of step's pairs in the same pass
        li = np.ascontiguousarray(i, dtype=np.int64)
        commit_factorized(state, memory.joint, li, np.ascontiguousarray(fused, dtype=np.bool_))


_WARMED: list = []


def warm_up_joint_form() -> None:
    """Load (or compile) the link loop's form of the correlated joints
    (:data:`~resloc.cl.kernels_joint_links.JOINT_FORM`) and their rounds
    (:mod:`resloc.cl.kernels_joint_rounds`) once per process, by a small ``tracked``
    correction and one of a ring of robots: the strategies call it when they set up their
    state, before a run times its steps (the runner's warm-up loads the forms every option
    shares; these only a run of ``tracked`` or ``factorized`` needs)."""
    from resloc.cl.backend import backend

    if _WARMED or backend() != "numba":
        return
    _WARMED.append(True)
    from resloc.cl.kernels import fast_correct  # the dispatch imports the strategies
    from resloc.cl.kernels_inputs import pair_warm_up_batch
    from resloc.cl.memory import LinkMemory
    from resloc.cl.params import CLParams
    from resloc.filters.base import make_filter

    x, P, links = pair_warm_up_batch()
    memory = LinkMemory(2)
    memory.joint = JointCovariance(P, 2)
    fast_correct(make_filter("ckf"), x, P, links, CLParams(fusion="tracked"), memory)
    # and the joints' rounds (kernels_joint_rounds), which a team's step takes
    from resloc.cl.kernels_rounds import rounds_warm_up_batch

    x, P, links = rounds_warm_up_batch()
    memory = LinkMemory(len(x))
    memory.joint = JointCovariance(P, len(x))
    fast_correct(make_filter("ckf"), x, P, links, CLParams(fusion="tracked"), memory)
