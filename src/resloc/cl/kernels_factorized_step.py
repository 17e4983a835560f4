"""The once-per-step parts of ``factorized`` fusion, compiled: the prediction, the commit of
the kernel's records and the end of step's pair closing.

Each is the twin of a method of :class:`~resloc.cl.factorized.FactorizedCovariance` (a
batch's; a robot process's ``local`` factors stay numpy), used by the strategy
(:mod:`resloc.cl.fusion_methods`) when the backend is numba, and by the kernels' commit
(:func:`resloc.cl.kernels_joint.joint_commit`) after a compiled correction. The
prediction and the finish return None or False (nothing changed) when they do not apply,
and the reference runs.

===================================  ===================================================
function                             numpy twin
===================================  ===================================================
:func:`compiled_factorized_predict`  :meth:`~resloc.cl.factorized.FactorizedCovariance.predict`
:func:`commit_factorized`            the state ``FactorizedCovariance.update`` leaves,
                                     then :meth:`~resloc.cl.factorized.FactorizedCovariance.finish`
:func:`compiled_factorized_finish`   :meth:`~resloc.cl.factorized.FactorizedCovariance.finish`
===================================  ===================================================

The commit writes every factor once (``docs/performance.md``, "Factorized, per step"):
``A_i sigma_il`` or, for a pair that fused in either direction, the pair's closed factor
(its cross-covariance for the lower id, the identity for the higher id), which is what
``finish`` writes there; the finish then has nothing left to do. The closed values do not
depend on the factors ``finish`` overwrites, so the reference's ``finish`` after this commit
changes nothing; a reference update after it (a second correction of the step) clears
``pairs_closed`` and the compiled finish closes the pairs again, in place.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import backend, c_float
from resloc.cl.factorized import FactorizedCovariance
from resloc.cl.kernels_math import entries3, jit, jit_inline

__all__ = [
    "commit_factorized",
    "compiled_factorized_finish",
    "compiled_factorized_predict",
]


def compiled_factorized_predict(joint, x, u, dt: float, P_pred) -> np.ndarray | None:
    """``FactorizedCovariance.predict`` compiled: ``sigma_il <- F_i sigma_il`` for every
    factor, the step's bookkeeping started; returns ``P_pred``."""
    if backend() != "numba" or not isinstance(joint, FactorizedCovariance) or joint.local:
        return None
    B = joint.B
    if np.shape(x) != (B, 3) or np.shape(u) != (B, 2):
        return None
    sig = np.array(joint.sig, dtype=float, order="C", copy=True)
    _left_multiply_factors(c_float(x), c_float(u), float(dt), sig)
    joint.sig = sig
    joint.start_step(P_pred)
    return P_pred


@jit
def _left_multiply_factors(x, u, dt, sig):
    """``sig[b, m] <- F_b sig[b, m]`` in place: rows 0, 1 of each factor plus ``F[p, 2]``
    times its row 2 (``F`` the unicycle's Jacobian, the identity elsewhere: the same sums as
    the 3 x 3 product's to the bit for finite entries). (Writing ``sig`` and ``sig_pred``
    in this loop, not copying, measured slower: 1.85 against 1.65 us at 17 robots; the
    copies are ``memcpy``.)"""
    for b in range(sig.shape[0]):
        v = u[b, 0]
        f0 = -v * math.sin(x[b, 2]) * dt  # (as kernels_fusion_step.unicycle_jacobian_into)
        f1 = v * math.cos(x[b, 2]) * dt
        for m in range(sig.shape[1]):
            for q in range(3):
                s2q = sig[b, m, 2, q]
                sig[b, m, 0, q] = sig[b, m, 0, q] + f0 * s2q
                sig[b, m, 1, q] = sig[b, m, 1, q] + f1 * s2q


def commit_factorized(state, joint, obs: np.ndarray, link_fused: np.ndarray) -> None:
    """Hand the kernel's records (``state``, a :class:`~resloc.cl.kernels_joint.KernelJoint`
    of ``factorized``; ``obs``, ``link_fused``: the links' observers and fused flags, (E,))
    to ``joint``: ``A``, ``B`` and the pairs that fused as ``FactorizedCovariance.update``
    leaves them, and the factors as its ``finish`` leaves them (``joint.pairs_closed``
    set: the compiled finish has nothing left to do)."""
    sig = np.empty_like(state.sig)
    _commit_factors(
        state.A, state.sig, state.sig_pred, c_float(joint.P_pred), state.Bij, state.gains,
        obs, state.nbr, link_fused, state.fused, state.N, sig, state.Bm,
    )  # fmt: skip
    joint.sig = sig
    joint.A = state.A
    joint.Bm = state.Bm
    joint.fused = state.fused
    joint.pairs_closed = True


@jit
def _commit_factors(A, sig, sig_pred, P_pred, Bij, gains, obs, nbr, link_fused, fused, N,
                    sig_out, Bm):  # fmt: skip
    """The products the ``factorized`` kernel deferred and the end of step in one pass:
    each fused link's ``B_ij`` (recorded as ``-K H_j``) times the gains ``G`` of i's later
    fused links, added into ``Bm[i, j % N]`` (rows sorted by observer); then every factor
    ``sig_out[b, m]``: for a pair that fused in either direction (``fused``: (B, N)), the
    pair's closed factor (:func:`_closed_factor`), else ``A_b sig[b, m]``.
    Twin: ``FactorizedCovariance.update`` (its products), then ``finish``."""
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    e = obs.shape[0] - 1
    while e >= 0:  # robot by robot from the last row: S = the product of the later gains
        i = obs[e]
        S = identity
        while e >= 0 and obs[e] == i:
            if link_fused[e]:
                _add_product(S, Bij[e], Bm[i, nbr[e] % N])
                S = _product(S, gains[e])
            e -= 1
    for b in range(sig.shape[0]):
        lb = b % N
        t0 = b - lb
        a = entries3(A[b])
        for m in range(N):
            c = t0 + m
            if fused[b, m] or fused[c, lb]:
                if b < c:
                    _closed_factor(A, Bm, P_pred, sig_pred, b, c, lb, m, sig_out[b, m])
                else:  # the pair's higher id (the reference writes it last)
                    for p in range(3):
                        for q in range(3):
                            sig_out[b, m, p, q] = 1.0 if p == q else 0.0
                continue
            _set_product(a, sig[b, m], sig_out[b, m])


@jit_inline
def _product(S, M):
    """``S M`` of a 3 x 3 ``S`` given as a 9-tuple by row and a 3 x 3 array, as a 9-tuple
    (the sums of :func:`~resloc.cl.kernels_math.mul3`, in its order)."""
    m = entries3(M)
    return (
        S[0] * m[0] + S[1] * m[3] + S[2] * m[6],
        S[0] * m[1] + S[1] * m[4] + S[2] * m[7],
        S[0] * m[2] + S[1] * m[5] + S[2] * m[8],
        S[3] * m[0] + S[4] * m[3] + S[5] * m[6],
        S[3] * m[1] + S[4] * m[4] + S[5] * m[7],
        S[3] * m[2] + S[4] * m[5] + S[5] * m[8],
        S[6] * m[0] + S[7] * m[3] + S[8] * m[6],
        S[6] * m[1] + S[7] * m[4] + S[8] * m[7],
        S[6] * m[2] + S[7] * m[5] + S[8] * m[8],
    )


@jit_inline
def _set_product(S, M, out):
    """``out = S M`` (``S`` a 9-tuple by row; the sums of ``mul3``, in its order)."""
    for q in range(3):
        m0 = M[0, q]
        m1 = M[1, q]
        m2 = M[2, q]
        out[0, q] = S[0] * m0 + S[1] * m1 + S[2] * m2
        out[1, q] = S[3] * m0 + S[4] * m1 + S[5] * m2
        out[2, q] = S[6] * m0 + S[7] * m1 + S[8] * m2


@jit_inline
def _add_product(S, M, out):
    """``out += S M`` (``S`` a 9-tuple by row)."""
    for q in range(3):
        m0 = M[0, q]
        m1 = M[1, q]
        m2 = M[2, q]
        out[0, q] += S[0] * m0 + S[1] * m1 + S[2] * m2
        out[1, q] += S[3] * m0 + S[4] * m1 + S[5] * m2
        out[2, q] += S[6] * m0 + S[7] * m1 + S[8] * m2


def compiled_factorized_finish(joint) -> bool:
    """``FactorizedCovariance.finish`` compiled: for every pair of teammates that fused in
    either direction this step, the lower id keeps the pair's new cross-covariance
    (``_pair_cross``) as its factor, the higher id the identity. Nothing left to do when
    the compiled commit closed them (``joint.pairs_closed``, :func:`commit_factorized`);
    else in place, as the reference. False when it does not apply."""
    if backend() != "numba" or not isinstance(joint, FactorizedCovariance) or joint.local:
        return False
    if joint.B % joint.N:
        return False
    if getattr(joint, "pairs_closed", False):  # (a joint pickled before the flag: no)
        joint.pairs_closed = False  # (a later update of the step would need a new closing)
        return True
    sig = c_float(joint.sig)
    _close_pairs(
        np.ascontiguousarray(joint.fused, dtype=np.bool_), c_float(joint.A),
        c_float(joint.Bm), c_float(joint.P_pred), c_float(joint.sig_pred), joint.N, sig,
    )  # fmt: skip
    joint.sig = sig
    return True


@jit
def _close_pairs(fused, A, Bm, P_pred, sig_pred, N, sig):
    """Twin of ``FactorizedCovariance.finish``: ``sig[a, lc]`` the pair's cross-covariance
    (:func:`_closed_factor`) and ``sig[c, la]`` the identity for every pair ``a <= c`` of a
    team that fused in either direction (``fused``: (B, N)), in place."""
    for t in range(A.shape[0] // N):
        for la in range(N):
            a = t * N + la
            for lc in range(la, N):
                c = t * N + lc
                if not (fused[a, lc] or fused[c, la]):
                    continue
                _closed_factor(A, Bm, P_pred, sig_pred, a, c, la, lc, sig[a, lc])
                for p in range(3):
                    for q in range(3):
                        sig[c, la, p, q] = 1.0 if p == q else 0.0


#: Entries below this in magnitude: a product of three 3 x 3 matrices of them is finite, so
#: a term that a zero block multiplies is exactly zero (``0 * inf`` would be ``nan``).
_SMALL = 1e100


@jit_inline
def _small(M):
    """Every entry of ``M`` (a 9-tuple) below :data:`_SMALL` in magnitude (not ``nan``)."""
    ok = True
    for k in range(9):
        ok &= abs(M[k]) < _SMALL
    return ok


@jit_inline
def _zero(M):
    """Every entry of ``M`` (a 9-tuple) zero."""
    ok = True
    for k in range(9):
        ok &= M[k] == 0.0
    return ok


@jit_inline
def _mul(X, Y):
    """``X Y`` of 3 x 3 matrices given as 9-tuples by row (the sums of
    :func:`~resloc.cl.kernels_math.mul3`, in its order)."""
    return (
        X[0] * Y[0] + X[1] * Y[3] + X[2] * Y[6],
        X[0] * Y[1] + X[1] * Y[4] + X[2] * Y[7],
        X[0] * Y[2] + X[1] * Y[5] + X[2] * Y[8],
        X[3] * Y[0] + X[4] * Y[3] + X[5] * Y[6],
        X[3] * Y[1] + X[4] * Y[4] + X[5] * Y[7],
        X[3] * Y[2] + X[4] * Y[5] + X[5] * Y[8],
        X[6] * Y[0] + X[7] * Y[3] + X[8] * Y[6],
        X[6] * Y[1] + X[7] * Y[4] + X[8] * Y[7],
        X[6] * Y[2] + X[7] * Y[5] + X[8] * Y[8],
    )


@jit_inline
def _mul_t(X, Y):
    """``X Y^T`` of 3 x 3 matrices given as 9-tuples by row (the sums of
    :func:`~resloc.cl.kernels_math.mul3_t`, in its order)."""
    return (
        X[0] * Y[0] + X[1] * Y[1] + X[2] * Y[2],
        X[0] * Y[3] + X[1] * Y[4] + X[2] * Y[5],
        X[0] * Y[6] + X[1] * Y[7] + X[2] * Y[8],
        X[3] * Y[0] + X[4] * Y[1] + X[5] * Y[2],
        X[3] * Y[3] + X[4] * Y[4] + X[5] * Y[5],
        X[3] * Y[6] + X[4] * Y[7] + X[5] * Y[8],
        X[6] * Y[0] + X[7] * Y[1] + X[8] * Y[2],
        X[6] * Y[3] + X[7] * Y[4] + X[8] * Y[5],
        X[6] * Y[6] + X[7] * Y[7] + X[8] * Y[8],
    )


@jit_inline
def _add(X, Y):
    return (
        X[0] + Y[0], X[1] + Y[1], X[2] + Y[2], X[3] + Y[3], X[4] + Y[4], X[5] + Y[5],
        X[6] + Y[6], X[7] + Y[7], X[8] + Y[8],
    )  # fmt: skip


@jit_inline
def _closed_factor(A, Bm, P_pred, sig_pred, a, c, la, lc, out):
    """The new cross-covariance of the pair ``a < c`` (local indices ``la``, ``lc``) into
    ``out``: ``[A_a, B_ac] [[P_a, P_ac], [P_ca, P_c]]_pred [B_ca, A_c]^T`` with ``P_ac =
    sigma_ac sigma_ca^T`` (pred), the four terms summed in the reference's order (in
    9-tuples: registers, not scratch arrays). A pair that fused in one direction only has
    a zero ``B`` (``B_ca`` or ``B_ac``): its two terms are exactly zero when the other
    factors are small (:func:`_small`), and are skipped (most pairs of a step: 60 of 69
    in the bench's step 150), the same sums to the value.
    Twin: ``resloc.cl.factorized._pair_cross``."""
    P_ac = _mul_t(entries3(sig_pred[a, lc]), entries3(sig_pred[c, la]))
    A_a = entries3(A[a])
    A_c = entries3(A[c])
    B_ac = entries3(Bm[a, lc])
    B_ca = entries3(Bm[c, la])
    P_a = entries3(P_pred[a])
    P_c = entries3(P_pred[c])
    if _zero(B_ca) and _small(A_a) and _small(P_a) and _small(B_ac) and _small(P_ac):
        # A_a P_ac A_c^T + B_ac P_c A_c^T
        C = _add(_mul_t(_mul(A_a, P_ac), A_c), _mul_t(_mul(B_ac, P_c), A_c))
    elif _zero(B_ac) and _small(P_ac) and _small(B_ca) and _small(P_c) and _small(A_c):
        # A_a P_a B_ca^T + A_a P_ac A_c^T
        C = _add(_mul_t(_mul(A_a, P_a), B_ca), _mul_t(_mul(A_a, P_ac), A_c))
    else:
        C = _mul_t(_mul(A_a, P_a), B_ca)  # A_a P_a B_ca^T
        C = _add(C, _mul_t(_mul(A_a, P_ac), A_c))  # + A_a P_ac A_c^T
        C = _add(C, _mul_t(_mul_t(B_ac, P_ac), B_ca))  # + B_ac P_ac^T B_ca^T
        C = _add(C, _mul_t(_mul(B_ac, P_c), A_c))  # + B_ac P_c A_c^T
    for p in range(3):
        for q in range(3):
            out[p, q] = C[3 * p + q]
