"""The team's common rigid-body ("gauge") error, tracked: the ``gauge`` fusion method.

With relative measurements only, the team's common rigid-body error is unobservable: range
and bearing between two robots do not change when the whole team is translated by ``t`` and
rotated by ``phi`` about the origin, so for every link

    ``H_i J_i + H_j J_j = 0``,  ``J_i = [[1, 0, -y_i], [0, 1, x_i], [0, 0, 1]]``

(:func:`gauge_jacobian` maps the rigid-body error ``g = (t_x, t_y, phi)`` into robot i's pose
error; eq. 3 and its Jacobians): ``[J_1; ...; J_N]`` spans the unobservable subspace of
relative-measurement CL (Huang, Mourikis & Roumeliotis, Autonomous Robots 2011). The paper's
naive fusion forgets this: it treats a neighbour's estimate as an independent absolute fix,
so its covariances shrink below the team's common error, which no relative measurement can
reduce. Measured (17 robots, clean arc-turn, CKF, naive fusion): NEES 764 against the true
error, **2.05** against the error with the team's least-squares rigid-body error removed:
the naive covariance ``D_i`` is consistent for the relative error and misses the common one
only.

The ``gauge`` method keeps the paper's estimates and filters (same gains, same relative
accuracy, same detector and trigger) and tracks what they miss: the covariance ``G`` of the
team's gauge error ``g = sum_i L_i e_i``, ``L_i = (sum_l J_l^T J_l)^{-1} J_i^T`` (the
least-squares rigid-body fit of the errors). A robot's consistent covariance is
``P_i = D_i + J_i G J_i^T`` (:meth:`GaugeCovariance.reported`). Model: errors
``e_i = J_i g + r_i`` with relative parts ``r_i`` uncorrelated with each other and with ``g``,
``cov(r_i) = D_i`` (the naive covariance, measured consistent above).

* start: ``G_0 = sum_i L_i P_0,i L_i^T`` (independent initial errors);
* prediction: odometry noise moves the fit, ``G += sum_i L_i Q_i L_i^T``;
* correction: every robot's step is linear in the predicted errors,
  ``e_i <- A_i e_i + sum_j B_ij e_j + n_i`` (``A_i`` the product of its ``I - K H_i``,
  ``B_ij = -K H_j`` then left-multiplied by i's later gains, ``n_i`` its measurement
  noise ``K R K^T`` propagated alike). Because ``A_i J_i + sum_j B_ij J_j = J_i`` (first
  order), the fit moves only by what leaks from the relative parts:
  ``g <- g + sum_m Delta_m r_m + sum_i L_i n_i`` with robot m's leak
  ``Delta_m = L_m (A_m - I) + sum_{i fused m} L_i B_im``, so
  ``G += sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T``. A symmetric exchange leaks
  nothing (the pair's mean is kept); a one-sided one moves the team.

Every addition to ``G`` is a sum over robots of terms each robot computes from its own
quantities, its ``L_i`` and, for ``Delta_m``, the ``L_i B_im`` of the robots that fused m's
estimate (9 numbers sent back on the link that delivered): one average-consensus quantity
per step (``(sum_l J_l^T J_l)`` is another, for ``L_i``). By default this module computes
those sums exactly per team (the value an average consensus converges to); with ``rounds``
every robot runs the dynamic average consensus itself over the communication graph and has
its own ``G`` (``estimator.gauge_sums = "consensus"``, ``docs/beyond.md``). The estimates
never depend on ``G``.
"""

from __future__ import annotations

import enum

import numpy as np

from resloc.cl.connectivity import MetropolisMixer, metropolis_mix_one
from resloc.cl.tracking import identity_stack, update_map
from resloc.filters.base import Moments
from resloc.linalg import solve_spd, symmetrize

__all__ = ["GaugeCovariance", "GaugeSums", "gauge_jacobian"]


class GaugeSums(enum.StrEnum):
    """How gauge fusion's team sums are formed: ``exact`` (what an average consensus
    converges to) or ``consensus`` (each robot's own, by neighbour exchanges)."""

    EXACT = "exact"
    CONSENSUS = "consensus"


def gauge_jacobian(x: np.ndarray) -> np.ndarray:
    """``J_i``: robot poses' response to a rigid motion ``(t_x, t_y, phi)`` about the origin.

    Parameters
    ----------
    x : ndarray, shape (B, 3)

    Returns
    -------
    ndarray, shape (B, 3, 3)
        ``[[1, 0, -y], [0, 1, x], [0, 0, 1]]``.
    """
    J = np.zeros((x.shape[0], 3, 3))
    J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
    J[:, 0, 2] = -x[:, 1]
    J[:, 1, 2] = x[:, 0]
    return J


class GaugeCovariance:
    """Gauge covariances ``G`` of T teams of N robots (robot ``b`` is ``b % N`` of team
    ``b // N``), with one step's bookkeeping.

    Parameters
    ----------
    x0 : ndarray, shape (T * N, 3)
        Initial estimates.
    P0 : ndarray, shape (T * N, 3, 3)
        Initial covariances (independent across robots).
    robots : int
        Team size N.
    rounds : int, optional
        None (default): the team sums are exact (what a consensus converges to). An int:
        every robot keeps its own estimates of the two team averages (``J^T J`` and the
        cumulative ``G`` contributions) by dynamic average consensus (Zhu & Martinez 2010,
        Metropolis weights), ``rounds`` neighbour exchanges per step (:meth:`exchange`);
        then each robot has its own ``G_b = N * mean``.
    local : bool
        One robot's process (:class:`~resloc.cl.node.RobotNode`, batch size 1): consensus
        only; the acknowledgements of the robots that fused this robot's estimate arrive
        from outside (:meth:`acks` to send, :meth:`close` with what was received) and the
        consensus runs one exchange per :meth:`mix_local` call.
    """

    def __init__(
        self,
        x0: np.ndarray,
        P0: np.ndarray,
        robots: int,
        rounds: int | None = None,
        local: bool = False,
    ) -> None:
        self.N = int(robots)
        self.local = bool(local)
        if self.local:
            rounds = 1 if rounds is None else rounds
        elif len(P0) % self.N:
            raise ValueError(
                f"batch of {len(P0)} robots is not a multiple of the team size {self.N}"
            )
        if rounds is not None and int(rounds) < 1:
            raise ValueError(f"rounds must be >= 1, got {rounds}")
        self.B = len(P0)
        self.T = max(self.B // self.N, 1)
        self.rounds = None if rounds is None else int(rounds)
        self.messages = 0
        #: Prediction and finish steps run by the compiled twins (:mod:`resloc.cl.kernels_gauge`).
        self.compiled_steps = 0
        #: Reported covariances formed by the compiled twin (:mod:`resloc.cl.kernels_gauge`).
        self.compiled_reports = 0
        #: The compiled twins' preallocated step arrays
        #: (:class:`resloc.cl.kernels_gauge.GaugeBuffers`), made on their first step.
        self.kernel_buffers = None
        if self.rounds is None:
            self.G = np.zeros((self.T, 3, 3))
        else:  # per-robot consensus states: own value until the first exchange
            J = gauge_jacobian(x0)
            self.phi_M = np.swapaxes(J, -1, -2) @ J
            self.M_hat = self.phi_M.copy()
            self.C_hat = np.zeros((self.B, 3, 3))
        L = self._fit(x0)
        self._add(L @ P0 @ np.swapaxes(L, -1, -2))
        self._start_step(L, P0)

    # ------------------------------------------------------------------ helpers
    def _fit(self, x: np.ndarray) -> np.ndarray:
        """``L_i = (sum_l J_l^T J_l)^{-1} J_i^T`` of every robot (its team's fit), (B, 3, 3).

        With consensus, ``sum_l J_l^T J_l`` is the robot's own estimate ``N * M_hat``
        (its tracker follows the change of its own signal at once).
        """
        J = gauge_jacobian(x)
        Jt = np.swapaxes(J, -1, -2)
        JtJ = Jt @ J
        if self.rounds is None:  # one inverse per team
            M = self._team_sum(JtJ)
            return solve_spd(M, np.broadcast_to(np.eye(3), M.shape).copy())[self._team()] @ Jt
        self.M_hat = self.M_hat + JtJ - self.phi_M
        self.phi_M = JtJ
        return solve_spd(self.N * self.M_hat, Jt)

    def _team(self) -> np.ndarray:
        return np.arange(self.B) // self.N

    def _team_sum(self, terms: np.ndarray) -> np.ndarray:
        return terms.reshape(self.T, self.N, 3, 3).sum(axis=1)

    def _add(self, terms: np.ndarray) -> None:
        """Add every robot's contribution ``terms: (B, 3, 3)`` to its team's ``G``."""
        if self.rounds is None:
            self.G = symmetrize(self.G + self._team_sum(terms))
        else:  # dynamic average consensus: the tracker follows its own signal's change
            self.C_hat = self.C_hat + terms

    def robot_G(self) -> np.ndarray:
        """``G`` as each robot knows it, shape (B, 3, 3)."""
        if self.rounds is None:
            return self.G[self._team()]
        return symmetrize(self.N * self.C_hat)

    def exchange(self, i: np.ndarray, j: np.ndarray) -> None:
        """Consensus rounds on this step's communication edges ``(i, j)`` (no-op when exact).

        Parameters
        ----------
        i, j : ndarray of int, shape (E,)
            Links that can carry a message this step.
        """
        if self.rounds is None:
            return
        graph = MetropolisMixer(i, j, self.B)
        for _ in range(self.rounds):
            self.M_hat = graph.mix(self.M_hat)
            self.C_hat = graph.mix(self.C_hat)
            self.messages += graph.messages

    def _start_step(self, L: np.ndarray, D_pred: np.ndarray) -> None:
        self.L = L
        self.D_pred = D_pred.copy()
        self.A = identity_stack(self.B)
        self.noise = np.zeros((self.B, 3, 3))
        # This step's fused links: observer, neighbour, B_ij (kept current with i's gains).
        self.obs = np.empty(0, dtype=np.int64)
        self.nbr = np.empty(0, dtype=np.int64)
        self.Bij = np.empty((0, 3, 3))

    def reported(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The consistent covariances ``P_i = D_i + J_i G J_i^T`` of estimates ``x``.

        Parameters
        ----------
        x : ndarray, shape (B, 3)
        P : ndarray, shape (B, 3, 3)
            The filters' covariances ``D_i`` (relative part).

        Returns
        -------
        ndarray, shape (B, 3, 3)
        """
        J = gauge_jacobian(x)
        return symmetrize(P + J @ self.robot_G() @ np.swapaxes(J, -1, -2))

    # ------------------------------------------------------------------ step
    def predict(
        self, x: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray, P_pred: np.ndarray
    ) -> np.ndarray:
        """Prediction: ``G += sum_i L_i Q_i L_i^T`` (``g`` itself is constant under the motion).

        Parameters
        ----------
        x : ndarray, shape (B, 3)
            Estimates before the prediction (the point ``Q`` was linearized at).
        u : ndarray, shape (B, 2)
            Unused (``F_i J_i(x) = J_i(f(x))``: a rigid motion of the whole team commutes
            with the unicycle model).
        dt : float
            Unused.
        Q : ndarray, shape (B, 3, 3)
            Process noise of every robot.
        P_pred : ndarray, shape (B, 3, 3)
            The filters' predicted covariances ``D_i``.

        Returns
        -------
        ndarray, shape (B, 3, 3)
            ``P_pred`` unchanged.
        """
        del u, dt
        L = self._fit(x)
        self._add(L @ Q @ np.swapaxes(L, -1, -2))
        self._start_step(L, P_pred)
        return P_pred

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
        P_new : ndarray, shape (E, 3, 3)
            The filters' updated covariances.

        Returns
        -------
        ndarray, shape (E, 3, 3)
            ``P_new`` unchanged (the estimates and ``D_i`` are the filters').
        """
        K, G_i, KH_j = update_map(m, x_i, x_j)
        if len(self.obs):  # i's earlier B_ik this step see i's new gain
            row = np.full(self.B, -1)
            row[i] = np.arange(len(i))
            mine = row[self.obs] >= 0
            self.Bij[mine] = G_i[row[self.obs[mine]]] @ self.Bij[mine]
        self.A[i] = G_i @ self.A[i]
        self.noise[i] = G_i @ self.noise[i] @ np.swapaxes(G_i, -1, -2) + K @ R @ (
            np.swapaxes(K, -1, -2)
        )
        self.obs = np.concatenate([self.obs, i])
        self.nbr = np.concatenate([self.nbr, j])
        self.Bij = np.concatenate([self.Bij, -KH_j])
        return P_new

    def finish(self, P: np.ndarray) -> np.ndarray:
        """End of the correction: ``G += sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T``.

        Parameters
        ----------
        P : ndarray, shape (B, 3, 3)
            The filters' corrected covariances.

        Returns
        -------
        ndarray, shape (B, 3, 3)
            ``P`` unchanged.
        """
        if self.local:  # wait for the neighbours' acknowledgements (close)
            return P
        leak = self.L @ (self.A - np.eye(3))
        if len(self.obs):
            np.add.at(leak, self.nbr, self.acks()[1])
        self._close(leak)
        return P

    def acks(self) -> tuple[np.ndarray, np.ndarray]:
        """The acknowledgements this step's updates owe: ``L_i B_ij`` to each neighbour j.

        Returns
        -------
        j : ndarray of int, shape (E,)
            The neighbours whose estimates were fused (ids as given to :meth:`update`).
        ack : ndarray, shape (E, 3, 3)
        """
        return self.nbr.copy(), self.L[self.obs] @ self.Bij

    def close(self, received: np.ndarray) -> None:
        """End of a robot process's step (``local``): its leak with the acknowledgements
        ``received: (K, 3, 3)`` of the robots that fused its estimate this step."""
        if not self.local:
            raise ValueError("close() is for a local (one robot's) gauge; finish() closes a batch")
        leak = self.L @ (self.A - np.eye(3)) + np.asarray(received).reshape(-1, 3, 3).sum(axis=0)
        self._close(leak)

    def _close(self, leak: np.ndarray) -> None:
        T_ = np.swapaxes
        self._add(leak @ self.D_pred @ T_(leak, -1, -2) + self.L @ self.noise @ T_(self.L, -1, -2))

    def message(self) -> np.ndarray:
        """What a consensus exchange carries: ``[M_hat, C_hat]``, shape (B, 2, 3, 3)."""
        return np.stack([self.M_hat, self.C_hat], axis=1)

    def mix_local(self, degree: int, received: np.ndarray, degrees: np.ndarray) -> None:
        """One consensus exchange of a robot process (``local``).

        Parameters
        ----------
        degree : int
            This robot's number of neighbours in the exchange.
        received : ndarray, shape (K, 2, 3, 3)
            The neighbours' :meth:`message` (K = ``degree``).
        degrees : ndarray of int, shape (K,)
            Their numbers of neighbours (Metropolis weights need both ends).
        """
        state = self.message()[0]
        mixed = metropolis_mix_one(state, degree, np.asarray(received), np.asarray(degrees))
        self.M_hat, self.C_hat = mixed[None, 0], mixed[None, 1]
        self.messages += int(degree)
