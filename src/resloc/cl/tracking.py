"""Cross-covariance tracking: the team's joint covariance, kept exactly (to first order).

The ``tracked`` fusion method. A relative update of robot i from neighbour j's transmitted
(predicted) estimate is a Schmidt-Kalman update of ``x_i`` that *uses* the cross-covariance
``C_ij = cov(e_i, e_j)`` instead of assuming it is 0 (naive) or bounding it (CI):

the moments of ``z_ij`` come from the joint ``[[P_i, C_ij], [C_ij^T, P_j]]`` (sigma points of
the filter's own rule drawn from it, or the EKF's linearization), then the shared Kalman
update of ``x_i`` only (``x_j`` is a "consider" state: the paper's protocol updates the
observer only).

Bookkeeping over one step, as in the recursive decentralized CL of Luft, Schubert,
Roumeliotis & Burgard (IJRR 2018), which factorizes the same quantities so that each robot
stores only its own part: after the prediction the joint covariance of the predicted errors
``Sigma`` (``3N x 3N`` per team) is known; every robot's current error is a linear map of the
predicted errors plus its own measurement noise, ``e_i = M_i e_pred + w_i``. An update of i
from j (whose *predicted* estimate was transmitted) maps ``M_i <- (I - K H_i) M_i - K H_j E_j``
(``w_i``, i's own measurement noise, is independent of every other robot), and gives
``C_ij = M_i Sigma[:, j]``. At the end of the step the off-diagonal blocks become
``M Sigma M^T`` and the diagonal blocks the filters' corrected ``P_i``; the next prediction
maps ``Sigma_il <- F_i Sigma_il F_l^T`` (the diagonal: the filters' predicted ``P_i``).

This is the centralized-equivalent bookkeeping: it needs the team's joint covariance, which a
distributed team does not have. Luft et al.'s factorization ``Sigma_il = sigma_il sigma_li^T``
with an approximation for third robots is its distributed realization
(:mod:`resloc.cl.factorized`, ``fusion = "factorized"``). This module is the reference for what
cross-covariance tracking can achieve.
"""

from __future__ import annotations

import numpy as np

from resloc.angles import circular_mean, wrap_angle
from resloc.filters.base import Moments
from resloc.filters.update import kalman_gain
from resloc.linalg import cholesky_jitter, symmetrize
from resloc.models.measurement import range_bearing, range_bearing_jacobians
from resloc.models.motion import unicycle_state_jacobian

__all__ = ["JointCovariance", "identity_stack", "joint_moments", "update_map"]

_identity_template: list[np.ndarray] = [np.zeros((0, 3, 3))]


def identity_stack(B: int) -> np.ndarray:
    """``B`` 3 x 3 identities, shape (B, 3, 3): a new array, copied from a template kept
    for the last ``B`` (a step's bookkeeping starts from one; ``np.broadcast_to(np.eye(3),
    ...).copy()`` costs several times the copy at a team's size)."""
    template = _identity_template[0]
    if len(template) != B:
        template = _identity_template[0] = np.repeat(np.eye(3)[None], B, axis=0)
    return template.copy()


def update_map(m: Moments, x_i: np.ndarray, x_j: np.ndarray):
    """The linear map of one relative update, ``e_i <- (I - K H_i) e_i - K H_j e_j - K v``.

    Parameters
    ----------
    m : Moments
        The moments the update used (its gain ``K = P^xz S^{-1}``).
    x_i, x_j : ndarray, shape (E, 3)
        The estimates the Jacobians are taken at (eq. 3; i's before the update).

    Returns
    -------
    K : ndarray, shape (E, 3, 2)
    G : ndarray, shape (E, 3, 3)
        ``I - K H_i``.
    KH_j : ndarray, shape (E, 3, 3)
        ``K H_j``.
    """
    K = kalman_gain(m.S, m.Pxz)
    H_i, H_j = range_bearing_jacobians(x_i, x_j)
    return K, np.eye(3) - K @ H_i, K @ H_j


def joint_moments(
    filt,
    x_i: np.ndarray,
    P_i: np.ndarray,
    x_j: np.ndarray,
    P_j: np.ndarray,
    C: np.ndarray,
    R: np.ndarray,
) -> Moments:
    """Moments of ``z_ij`` (eq. 3) under a correlated joint ``[[P_i, C], [C^T, P_j]]``.

    A sigma-point filter draws its 6-D points (its own rule) from the joint covariance; the
    EKF linearizes: ``S = H J H^T + R``, ``P^xz = J[:3] H^T``. Shared by ``tracked``
    (:class:`JointCovariance`) and ``factorized`` (:mod:`resloc.cl.factorized`) fusion.

    Parameters
    ----------
    filt : GaussianFilter
    x_i, x_j : ndarray, shape (E, 3)
        Observer's current estimate, neighbour's transmitted estimate.
    P_i, P_j, C : ndarray, shape (E, 3, 3)
        Their covariances and cross-covariance ``cov(e_i, e_j)``.
    R : ndarray, shape (2, 2)

    Returns
    -------
    Moments
        Without Jacobians (the update is ``P - K S K^T``).
    """
    E = len(x_i)
    J = np.empty((E, 6, 6))
    J[:, :3, :3] = P_i
    J[:, :3, 3:] = C
    J[:, 3:, :3] = np.swapaxes(C, -1, -2)
    J[:, 3:, 3:] = P_j
    J = symmetrize(J)
    rule = getattr(filt, "rule6", None)
    if rule is None:  # EKF: linearization
        H_i, H_j = range_bearing_jacobians(x_i, x_j)
        H = np.concatenate([H_i, H_j], axis=2)  # (E, 2, 6)
        S = H @ J @ np.swapaxes(H, -1, -2) + R
        Pxz = J[:, :3, :] @ np.swapaxes(H, -1, -2)
        return Moments(range_bearing(x_i, x_j), symmetrize(S), Pxz)
    L = cholesky_jitter(J)
    offsets = rule.unit[None] @ np.swapaxes(L, -1, -2)  # (E, m, 6)
    Z = range_bearing(x_i[:, None, :] + offsets[..., :3], x_j[:, None, :] + offsets[..., 3:])
    z_hat = np.empty((E, 2))
    z_hat[:, 0] = Z[..., 0] @ rule.Wm
    z_hat[:, 1] = (
        circular_mean(Z[..., 1], rule.Wm)
        if getattr(filt, "circular", True)
        else wrap_angle(Z[..., 1] @ rule.Wm)
    )
    dZ = Z - z_hat[:, None, :]
    dZ[..., 1] = wrap_angle(dZ[..., 1])
    dX = offsets[..., :3] - (rule.Wm @ offsets[..., :3])[:, None, :]
    dZw = np.swapaxes(dZ * rule.Wc[None, :, None], -1, -2)  # (E, 2, m)
    S = dZw @ dZ + R
    Pxz = np.swapaxes(dZw @ dX, -1, -2)
    return Moments(z_hat, symmetrize(S), Pxz)


class JointCovariance:
    """The joint covariance of T independent teams of N robots, with one step's bookkeeping.

    Robot ``b`` of the batch is robot ``b % N`` of team ``b // N`` (the simulator's layout).

    Parameters
    ----------
    P0 : ndarray, shape (T * N, 3, 3)
        Initial covariances (initial errors independent across robots).
    robots : int
        Team size N.
    """

    #: ``(sigma, spare)``: a copy of the joint ``sigma`` the compiled prediction wrote, which
    #: the next compiled correction takes as its rows of ``M Sigma``
    #: (:func:`resloc.cl.kernels_tracked_step.take_spare_rows`).
    spare_rows: tuple[np.ndarray, np.ndarray] | None = None
    #: The compiled corrections' scratch arrays, kept for the joint's steps
    #: (:func:`resloc.cl.kernels_joint.kernel_scratch`).
    compiled_scratch: tuple | None = None

    def __init__(self, P0: np.ndarray, robots: int) -> None:
        B = P0.shape[0]
        self.N = int(robots)
        if B % self.N:
            raise ValueError(f"batch of {B} robots is not a multiple of the team size {self.N}")
        self.T = B // self.N
        n3 = 3 * self.N
        self.sigma = np.zeros((self.T, n3, n3))
        self._set_diagonal(self.sigma, P0)
        self.start_step()

    # ------------------------------------------------------------------ layout helpers
    def _set_diagonal(self, sigma: np.ndarray, P: np.ndarray) -> None:
        v = sigma.reshape(self.T, self.N, 3, self.N, 3)
        r = np.arange(self.N)
        v[:, r, :, r, :] = np.swapaxes(P.reshape(self.T, self.N, 3, 3), 0, 1)

    def start_step(self) -> None:
        """A new step's bookkeeping (``M`` the identity, no noise, no records), after the
        prediction wrote ``sigma`` (here or in the compiled prediction)."""
        if getattr(self, "_identity_M", None) is None:
            # every robot's M_b = E_b (its own block the identity), built once (T and N do
            # not change): a step starts from a copy
            B, n3 = self.T * self.N, 3 * self.N
            identity = np.zeros((B, 3, n3))
            b = np.arange(B)
            local = b % self.N
            for a in range(3):
                identity[b, a, 3 * local + a] = 1.0
            self._identity_M = identity
        # M and the noise are built where first read (the properties below): a compiled
        # step starts twice (its finish, then the next prediction) and hands both over from
        # its kernel (resloc.cl.kernels_joint.joint_commit), so eager copies were thrown away
        self._M: np.ndarray | None = None
        self._blocks: tuple | None = None  # M by its non-zero blocks (set_blocks)
        self._noise: np.ndarray | None = None
        self.updates = 0  # updates recorded since (M, noise) were reset
        # M Sigma, (B, 3, 3N), where a compiled correction kept it (its commit,
        # resloc.cl.kernels_joint.joint_commit) for the compiled finish; None after any
        # other change of M (this class never reads it)
        self.m_sigma: np.ndarray | None = None
        # (sigma, diagonal): what finish would make of the step's records, where a compiled
        # commit computed it (resloc.cl.kernels_tracked_step); None after update or a new
        # M or noise (this class never reads it)
        self.end_of_step: tuple[np.ndarray, np.ndarray] | None = None

    def set_blocks(
        self, A: np.ndarray, Bij: np.ndarray, i: np.ndarray, j: np.ndarray, fused: np.ndarray
    ) -> None:
        """Set ``M`` by its non-zero 3 x 3 blocks, built dense only where read (a compiled
        correction's records, :mod:`resloc.cl.kernels_tracked_step`): robot b's ``A[b]``
        (B, 3, 3) at its own column, and for each link ``e`` with ``fused[e]`` (E,) bool,
        ``Bij[e]`` (E, 3, 3) added at column ``j[e]`` of robot ``i[e]`` ((E,) batch
        indices)."""
        self._M = None
        self._blocks = (A, Bij, i, j, fused)
        self.end_of_step = None

    @property
    def M(self) -> np.ndarray:
        """Every robot's map ``M_b`` (B, 3, 3N): its current error is ``M_b e_pred + w_b``
        (``E_b``, its own block the identity, where the step starts)."""
        if self._M is None:
            M = self._identity_M.copy()
            if self._blocks is not None:
                A, Bij, i, j, fused = self._blocks
                three = np.arange(3)
                b = np.arange(len(A))
                own = 3 * (b % self.N)[:, None] + three
                M[b[:, None, None], three[:, None], own[:, None, :]] = A
                e = np.flatnonzero(fused)
                cols = 3 * (np.asarray(j)[e] % self.N)[:, None] + three
                rows = np.asarray(i)[e][:, None, None]
                np.add.at(M, (rows, three[:, None], cols[:, None, :]), Bij[e])
                self._blocks = None
            self._M = M
        return self._M

    @M.setter
    def M(self, value: np.ndarray) -> None:
        self._M = value
        self._blocks = None
        self.end_of_step = None

    @property
    def noise(self) -> np.ndarray:
        """Every robot's propagated measurement noise ``cov(w_b)`` (B, 3, 3), zero where
        the step starts."""
        if self._noise is None:
            self._noise = np.zeros((self.T * self.N, 3, 3))
        return self._noise

    @noise.setter
    def noise(self, value: np.ndarray) -> None:
        self._noise = value
        self.end_of_step = None

    # ------------------------------------------------------------------ step
    def predict(
        self,
        x: np.ndarray,
        u: np.ndarray,
        dt: float,
        Q: np.ndarray,
        P_pred: np.ndarray | None = None,
    ) -> np.ndarray:
        """Time update ``Sigma <- F Sigma F^T + blockdiag(Q)`` (eqs. 1-2, linearized at ``x``).

        Parameters
        ----------
        x : ndarray, shape (B, 3)
            Estimates before the prediction.
        u : ndarray, shape (B, 2)
            Measured odometry.
        dt : float
        Q : ndarray, shape (B, 3, 3)
            Process noise.
        P_pred : ndarray, optional
            The filters' predicted covariances: ignored (the joint is the authority).

        Returns
        -------
        ndarray, shape (B, 3, 3)
            The predicted covariances ``P_i`` (the diagonal blocks), which the filters use.
        """
        F = unicycle_state_jacobian(x, u, dt).reshape(self.T, self.N, 3, 3)
        v = self.sigma.reshape(self.T, self.N, 3, self.N, 3)
        v = np.einsum("tiab,tibjc,tjdc->tiajd", F, v, F)
        v[:, np.arange(self.N), :, np.arange(self.N), :] += np.swapaxes(
            Q.reshape(self.T, self.N, 3, 3), 0, 1
        )
        self.sigma = symmetrize(v.reshape(self.sigma.shape))
        self.start_step()
        return self.diagonal()

    def diagonal(self) -> np.ndarray:
        """The diagonal blocks ``P_i``, shape (B, 3, 3)."""
        n3 = 3 * self.N
        index = getattr(self, "_diagonal_index", None)
        if index is None or len(index) != 9 * self.N:
            # flat positions of the diagonal blocks in a team's (3N, 3N) matrix, robot by
            # robot, row-major within a block: one gather per call
            block = 3 * np.arange(self.N)[:, None, None]
            a = np.arange(3)
            index = ((block + a[:, None]) * n3 + block + a[None, :]).ravel()
            self._diagonal_index = index
        return self.sigma.reshape(self.T, n3 * n3)[:, index].reshape(-1, 3, 3)

    def _m_sigma(self) -> np.ndarray:
        """``M_b Sigma`` of every robot, shape (B, 3, 3N) (one matrix product per team)."""
        n3 = 3 * self.N
        return (self.M.reshape(self.T, n3, n3) @ self.sigma).reshape(-1, 3, n3)

    def cross(self, i: np.ndarray, j: np.ndarray, ms: np.ndarray | None = None) -> np.ndarray:
        """``cov(e_i now, e_j predicted)`` for links ``(i, j)`` (batch indices).

        Returns
        -------
        ndarray, shape (E, 3, 3)
        """
        ms = self._m_sigma() if ms is None else ms
        cols = 3 * (j % self.N)[:, None] + np.arange(3)[None, :]  # (E, 3)
        return ms[i[:, None, None], np.arange(3)[None, :, None], cols[:, None, :]]

    def current(self, i: np.ndarray, ms: np.ndarray | None = None) -> np.ndarray:
        """Current covariances ``P_i = M_i Sigma M_i^T + cov(w_i)`` of robots ``i``, (E, 3, 3)."""
        ms = self._m_sigma() if ms is None else ms
        return symmetrize(ms[i] @ np.swapaxes(self.M[i], -1, -2) + self.noise[i])

    def moments(
        self,
        filt,
        x_i: np.ndarray,
        P_i: np.ndarray | None,
        x_j: np.ndarray,
        P_j: np.ndarray | None,
        i: np.ndarray,
        j: np.ndarray,
        R: np.ndarray,
    ) -> Moments:
        """Moments of ``z_ij`` under the tracked joint ``[[P_i, C_ij], [C_ij^T, P_j]]``.

        Parameters
        ----------
        filt : GaussianFilter
        x_i : ndarray, shape (E, 3)
            Current estimates of the observers.
        P_i, P_j : ignored
            The joint's own blocks are used (same signature as
            :meth:`~resloc.cl.factorized.FactorizedCovariance.moments`).
        x_j : ndarray, shape (E, 3)
            Transmitted (predicted) estimates.
        i, j : ndarray of int, shape (E,)
            Batch indices.
        R : ndarray, shape (2, 2)

        Returns
        -------
        Moments
            See :func:`joint_moments`.
        """
        ms = self._m_sigma()
        return joint_moments(
            filt, x_i, self.current(i, ms), x_j, self._block(j), self.cross(i, j, ms), R
        )

    def _block(self, j: np.ndarray) -> np.ndarray:
        """Predicted covariances ``Sigma_jj`` of robots ``j``, (E, 3, 3)."""
        t = j // self.N
        c = 3 * (j % self.N)[:, None] + np.arange(3)[None, :]
        return self.sigma[t[:, None, None], c[:, :, None], c[:, None, :]]

    def update(
        self,
        i: np.ndarray,
        j: np.ndarray,
        x_i: np.ndarray,
        x_j: np.ndarray,
        m: Moments,
        R: np.ndarray,
        P_new: np.ndarray | None = None,
    ) -> np.ndarray:
        """Record the updates of observers ``i`` (distinct) from ``j``'s predicted estimates.

        ``e_i <- (I - K H_i) e_i - K H_j e_j,pred - K v`` with the gain ``K = P^xz S^{-1}`` of
        the moments ``m`` the update used (:meth:`moments`) and the Jacobians at the means.

        P_new : ignored
            The filters' own updated covariances (the joint is the authority).

        Returns
        -------
        ndarray, shape (E, 3, 3)
            The observers' covariances after the update (positive semi-definite by
            construction for any gain).
        """
        K, IKH, KH_j = update_map(m, x_i, x_j)
        Mi = IKH @ self.M[i]
        cols = 3 * (j % self.N)[:, None] + np.arange(3)[None, :]  # (E, 3)
        e = np.arange(len(i))[:, None, None]
        Mi[e, np.arange(3)[None, :, None], cols[:, None, :]] -= KH_j
        self.M[i] = Mi
        self.m_sigma = None
        self.end_of_step = None
        self.updates += len(i)
        self.noise[i] = IKH @ self.noise[i] @ np.swapaxes(IKH, -1, -2) + K @ R @ np.swapaxes(
            K, -1, -2
        )
        return self.current(i)

    def finish(self, P: np.ndarray | None = None) -> np.ndarray:
        """End of the correction: ``Sigma <- M Sigma M^T + blockdiag(cov w)``.

        ``P`` (the filters' corrected covariances) is ignored: the joint is the authority.

        Returns
        -------
        ndarray, shape (B, 3, 3)
            The corrected covariances ``P_i`` (the diagonal blocks), which the filters keep.
            For the EKF they equal the filter's own ``P - K S K^T``; for the sigma-point
            filters they are its first-order counterpart, which keeps the joint covariance
            positive semi-definite by construction (mixing the points' ``P_i`` with
            linearized cross-covariances does not).
        """
        M = self.M.reshape(self.T, self.N * 3, 3 * self.N)
        sigma = M @ self.sigma @ np.swapaxes(M, -1, -2)
        v = sigma.reshape(self.T, self.N, 3, self.N, 3)
        v[:, np.arange(self.N), :, np.arange(self.N), :] += np.swapaxes(
            self.noise.reshape(self.T, self.N, 3, 3), 0, 1
        )
        self.sigma = symmetrize(sigma)
        self.start_step()
        return self.diagonal()
