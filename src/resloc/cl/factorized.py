"""Decentralized cross-covariance tracking by factors (the ``factorized`` fusion method).

The recursive decentralized cooperative localization of Luft, Schubert, Roumeliotis &
Burgard ("Recursive decentralized localization for multi-robot systems with asynchronous
pairwise communication", IJRR 2018), on the paper's protocol (robot i updates only itself
from ``z_ij`` and j's transmitted estimate).

Every robot i stores, besides ``(x_i, P_i)``, one 3x3 factor ``sigma_il`` per teammate l; the
cross-covariance is never stored whole, it is the product of two factors held by two robots:

    ``cov(e_i, e_l) = sigma_il sigma_li^T``  (initially 0: independent initial errors).

* prediction (local): ``sigma_il <- F_i sigma_il`` for every l, because
  ``F_i sigma_il sigma_li^T F_l^T`` is the predicted cross-covariance;
* a message of j on link (i, j) carries, besides ``(x_j, P_j)`` (predicted), the one factor
  ``sigma_ji`` that j keeps for i: 9 numbers; robot i forms ``C_ij = sigma_ij sigma_ji^T``
  and makes a Schmidt ("consider") update of ``x_i`` with the joint ``[[P_i, C_ij],
  [C_ij^T, P_j]]`` (:func:`~resloc.cl.tracking.joint_moments`: the filter's own points or
  linearization);
* that update maps i's error ``e_i <- G e_i - K H_j e_j + noise`` with ``G = I - K H_i``
  (Jacobians at the means): robot i left-multiplies every factor it holds by ``G`` and keeps
  ``B_ij = -K H_j`` (later updates of i in the same step left-multiply it too);
* end of the step, for every pair that fused in either direction, an acknowledgement on the
  link that just delivered carries the partner's ``(A, B, P_pred)`` (27 numbers): with
  ``A_i`` the product of i's ``G`` in the step, the pair's new cross-covariance is
  ``C = [A_i, B_ij] [[P_i, P_ij], [P_ji, P_j]]_pred [B_ji, A_j]^T``; the lower id stores
  ``sigma = C``, the other ``sigma = I`` (Luft et al.'s convention).

What a robot cannot know is dropped (Luft et al.'s approximation): the terms of its
cross-covariance with l that go through a third robot's error (``B_ij cov(e_j, e_l)``), i.e.
a robot's factors are corrected only by its own gain. :mod:`resloc.cl.tracking` keeps the
same quantities exactly (the team's joint covariance) and is the reference; this module is
what a team of separate robot processes can run. ``docs/beyond.md`` reports both.

Storage is dense per team (``(B, N, 3, 3)``: robot b's factor for teammate l), as in Luft
et al. (a robot keeps one factor per teammate).
"""

from __future__ import annotations

import numpy as np

from resloc.cl.tracking import identity_stack, joint_moments, update_map
from resloc.filters.base import Moments
from resloc.linalg import cholesky_jitter
from resloc.models.motion import unicycle_state_jacobian

__all__ = ["FactorizedCovariance"]


def valid_cross(
    P_i: np.ndarray, P_j: np.ndarray, C: np.ndarray, cap: float = 1.0 - 1e-6
) -> np.ndarray:
    """Shrink cross-covariances so that the joint ``[[P_i, C], [C^T, P_j]]`` stays valid.

    The joint is positive definite iff the correlation ``L_i^{-1} C L_j^{-T}`` (``L`` the
    Cholesky factors) has all singular values below 1. Approximate factors can violate it;
    those ``C`` are scaled by ``cap / sigma_max``.

    Parameters
    ----------
    P_i, P_j, C : ndarray, shape (E, 3, 3)

    Returns
    -------
    ndarray, shape (E, 3, 3)
    """
    Li, Lj = cholesky_jitter(P_i), cholesky_jitter(P_j)
    corr = np.linalg.solve(Li, np.swapaxes(np.linalg.solve(Lj, np.swapaxes(C, -1, -2)), -1, -2))
    smax = np.linalg.norm(corr, ord=2, axis=(-2, -1))
    scale = np.where(smax > cap, cap / np.maximum(smax, 1e-300), 1.0)
    return C * scale[:, None, None]


class FactorizedCovariance:
    """The factors ``sigma_il`` of T teams of N robots (robot ``b`` is ``b % N`` of team
    ``b // N``), with one step's bookkeeping.

    Parameters
    ----------
    batch : int
        Number of robots in the batch, ``T * N``.
    robots : int
        Team size N.
    local : bool
        One robot's process (:class:`~resloc.cl.node.RobotNode`, batch size 1): the factors
        its neighbours keep for it arrive with their transmissions (:meth:`receive`), and the
        end-of-step pair exchange runs by messages (:meth:`pair_message`,
        :meth:`close_pairs`) instead of :meth:`finish`.
    """

    def __init__(self, batch: int, robots: int, local: bool = False) -> None:
        self.N = int(robots)
        self.local = bool(local)
        if batch % self.N and not self.local:
            raise ValueError(f"batch of {batch} robots is not a multiple of the team size {self.N}")
        self.B = int(batch)
        self.sig = np.zeros((self.B, self.N, 3, 3))
        self.received: dict[int, np.ndarray] = {}
        self.start_step(np.zeros((self.B, 3, 3)))

    def start_step(self, P_pred: np.ndarray) -> None:
        """A new step's bookkeeping from the predicted covariances ``P_pred`` (B, 3, 3)
        (here or in the compiled prediction)."""
        self.sig_pred = self.sig.copy()  # what j's messages carry this step
        self.P_pred = P_pred.copy()
        self.A = identity_stack(self.B)
        self.Bm = np.zeros((self.B, self.N, 3, 3))
        self.fused = np.zeros((self.B, self.N), dtype=bool)
        # True where a compiled correction's commit (resloc.cl.kernels_factorized_step)
        # already wrote the factors finish writes; False after any other change (this class
        # never reads it: its finish would write the same values again)
        self.pairs_closed = False

    def _local(self, b: np.ndarray) -> np.ndarray:
        return np.asarray(b) % self.N

    # ------------------------------------------------------------------ step
    def predict(
        self, x: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray, P_pred: np.ndarray
    ) -> np.ndarray:
        """Time update of the factors, ``sigma_il <- F_i sigma_il`` (eq. 2 linearized at ``x``).

        Parameters
        ----------
        x : ndarray, shape (B, 3)
            Estimates before the prediction.
        u : ndarray, shape (B, 2)
        dt : float
        Q : ndarray, shape (B, 3, 3)
            Process noise (unused: it is independent across robots).
        P_pred : ndarray, shape (B, 3, 3)
            The filters' predicted covariances (kept: each robot's own filter is the
            authority on its ``P_i``).

        Returns
        -------
        ndarray, shape (B, 3, 3)
            ``P_pred`` unchanged.
        """
        del Q
        F = unicycle_state_jacobian(x, u, dt)
        self.sig = np.einsum("bac,blcd->blad", F, self.sig)
        self.start_step(P_pred)
        return P_pred

    def cross(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``cov(e_i now, e_j predicted) = sigma_ij sigma_ji,pred^T``, shape (E, 3, 3)."""
        if self.local:  # j's factor for this robot came with j's transmission
            missing = [int(b) for b in j if int(b) not in self.received]
            if missing:
                raise ValueError(
                    f"factorized fusion needs the factors neighbours {missing} keep for this "
                    "robot (RobotNode.correct's factor_nb: their factor_for(this robot))"
                )
            theirs = np.stack([self.received[int(b)] for b in j]).reshape(-1, 3, 3)
        else:
            theirs = self.sig_pred[j, self._local(i)]
        return self.sig[i, self._local(j)] @ np.swapaxes(theirs, -1, -2)

    def receive(self, j: np.ndarray, factors: np.ndarray) -> None:
        """``local``: the factors ``sigma_ji,pred`` that neighbours ``j: (E,)`` keep for this
        robot, as their transmissions carry them, ``factors: (E, 3, 3)``."""
        self.received = {int(b): f for b, f in zip(j, np.asarray(factors, float), strict=True)}

    def factor_for(self, j: int) -> np.ndarray:
        """``local``: what this robot's transmission to neighbour ``j`` carries besides its
        estimate: the factor it keeps for j, ``sigma_ij,pred``, shape (3, 3)."""
        return self.sig_pred[0, int(j) % self.N].copy()

    def pair_message(self, partner: int) -> np.ndarray:
        """``local``: what this robot sends to a partner of the step's pair exchange (a robot
        that fused its estimate or whose estimate it fused): ``[A, B_partner, P_pred,
        sigma_partner,pred]``, shape (4, 3, 3)."""
        lp = int(partner) % self.N
        return np.stack([self.A[0], self.Bm[0, lp], self.P_pred[0], self.sig_pred[0, lp]])

    def close_pairs(self, robot_id: int, messages: dict[int, np.ndarray]) -> None:
        """``local``: end of the step with the partners' :meth:`pair_message` (``{partner
        id: message}``): the lower id of each pair keeps the pair's cross-covariance as its
        factor, the higher id the identity (as :meth:`finish` does for a batch)."""
        me = int(robot_id)
        for partner, msg in messages.items():
            lp = int(partner) % self.N
            if me > int(partner):
                self.sig[0, lp] = np.eye(3)
                continue
            A_c, B_ca, P_c, sp_ca = np.asarray(msg, float).reshape(4, 3, 3)
            own = (self.A[0], self.Bm[0, lp], self.P_pred[0], self.sig_pred[0, lp])
            self.sig[0, lp] = _pair_cross(*own, A_c, B_ca, P_c, sp_ca)

    def moments(self, filt, x_i, P_i, x_j, P_j, i, j, R) -> Moments:
        """Moments of ``z_ij`` under ``[[P_i, C_ij], [C_ij^T, P_j]]``, ``C_ij`` from factors.

        Parameters
        ----------
        filt : GaussianFilter
        x_i, P_i : ndarray, shapes (E, 3), (E, 3, 3)
            Observers' current estimates.
        x_j, P_j : ndarray, shapes (E, 3), (E, 3, 3)
            Transmitted (predicted) estimates.
        i, j : ndarray of int, shape (E,)
        R : ndarray, shape (2, 2)
        """
        C = valid_cross(P_i, P_j, self.cross(i, j))
        return joint_moments(filt, x_i, P_i, x_j, P_j, C, R)

    def update(self, i, j, x_i, x_j, m: Moments, R, P_new: np.ndarray) -> np.ndarray:
        """Record the updates of observers ``i`` (distinct) from ``j``'s predicted estimates.

        Parameters
        ----------
        i, j : ndarray of int, shape (E,)
        x_i, x_j : ndarray, shape (E, 3)
            The estimates the update linearized at (i's before the update).
        m : Moments
            The moments the update used (its gain ``K = P^xz S^{-1}``).
        R : ndarray, shape (2, 2)
            Unused (i's measurement noise is independent of every other robot).
        P_new : ndarray, shape (E, 3, 3)
            The filters' updated covariances.

        Returns
        -------
        ndarray, shape (E, 3, 3)
            ``P_new`` unchanged.
        """
        del R
        _, G, KH_j = update_map(m, x_i, x_j)
        self.sig[i] = np.einsum("eac,elcd->elad", G, self.sig[i])
        self.Bm[i] = np.einsum("eac,elcd->elad", G, self.Bm[i])
        jl = self._local(j)
        self.Bm[i, jl] -= KH_j
        self.A[i] = G @ self.A[i]
        self.fused[i, jl] = True
        self.pairs_closed = False
        return P_new

    def finish(self, P: np.ndarray) -> np.ndarray:
        """End of the correction: the factors of every pair that fused this step.

        Parameters
        ----------
        P : ndarray, shape (B, 3, 3)
            The filters' corrected covariances.

        Returns
        -------
        ndarray, shape (B, 3, 3)
            ``P`` unchanged.
        """
        b, lj = np.nonzero(self.fused)
        if b.size and not self.local:
            team0 = b - self._local(b)
            a_ = np.minimum(b, team0 + lj)
            c_ = np.maximum(b, team0 + lj)
            pairs = np.unique(np.stack([a_, c_], axis=1), axis=0)
            a, c = pairs[:, 0], pairs[:, 1]
            la, lc = self._local(a), self._local(c)
            self.sig[a, lc] = _pair_cross(
                self.A[a], self.Bm[a, lc], self.P_pred[a], self.sig_pred[a, lc],
                self.A[c], self.Bm[c, la], self.P_pred[c], self.sig_pred[c, la],
            )  # fmt: skip
            self.sig[c, la] = np.eye(3)
        return P


def _pair_cross(A_a, B_ac, P_a, sig_ac, A_c, B_ca, P_c, sig_ca) -> np.ndarray:
    """The new cross-covariance of a pair ``(a, c)`` that fused in either direction,
    ``[A_a, B_ac] [[P_a, P_ac], [P_ca, P_c]]_pred [B_ca, A_c]^T`` with
    ``P_ac = sigma_ac,pred sigma_ca,pred^T`` (shapes (..., 3, 3))."""
    T = lambda M: np.swapaxes(M, -1, -2)  # noqa: E731
    P_ac = sig_ac @ T(sig_ca)
    return (
        A_a @ P_a @ T(B_ca) + A_a @ P_ac @ T(A_c) + B_ac @ T(P_ac) @ T(B_ca) + B_ac @ P_c @ T(A_c)
    )
