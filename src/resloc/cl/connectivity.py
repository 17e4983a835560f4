"""Distributed estimation of the algebraic connectivity ``lambda2(G)`` from neighbour exchanges.

The trigger's threshold (eq. 11) divides by ``lambda2(G)``, a property of the whole
communication graph that no robot of a distributed team knows. resloc estimates it with the
decentralized power iteration of Yang, Freeman, Gordon, Lynch, Srinivasa & Sukhatme
("Decentralized estimation and control of graph connectivity for mobile sensor networks",
Automatica 2010; the same family as Aragues et al., Automatica 2014), in discrete time. Each
robot i keeps one entry ``y_i`` of an estimate of the Fiedler vector and three average-
consensus trackers ``s_i ~ (mean y, mean y^2, mean y L y)``. Per exchange round it sends
``(y_i, s_i, deg_i)`` to its neighbours and then:

1. ``(L y)_i = deg_i y_i - sum_{j in N_i} y_j`` (local);
2. dynamic average consensus (Zhu & Martinez 2010) of ``phi_i = (y_i, y_i^2, y_i (L y)_i)``
   with Metropolis weights ``W_ij = 1 / (1 + max(deg_i, deg_j))`` and a small leak for
   robustness to topology changes: ``s <- W s + phi - phi_prev + leak (phi - s)``;
3. Yang et al.'s update ``y_i <- y_i - eps (k1 s_i,1 + k2 (L y)_i + k3 (s_i,2 - 1) y_i)``:
   the first term deflates the consensus direction, the second is the power step, the third
   normalizes (``k3 > k2 lambda2`` makes the Fiedler direction the stable equilibrium);
4. its own estimate, the centred Rayleigh quotient
   ``lambda2_i = mean(y L y) / (mean(y^2) - mean(y)^2)`` from its trackers. Yang et al. read
   ``k3 / k2 (1 - mean y^2)`` instead; the quotient is less sensitive to tracking bias (a bias
   of the leak affects numerator and denominator alike) and measured 2-5 times more accurate.

Gains: ``k2 = 1``, ``k3 = 2 n_max``, ``k1 = n_max`` and ``eps = 0.05 / n_max``, with
``n_max`` the team size (``lambda2 <= lambda_max <= N``: each robot knows its team size). The
state is warm-started from step to step, so a slowly changing graph needs only a few rounds
per step. Disconnected components run independently (the consensus never crosses them), so
each robot estimates the ``lambda2`` of its own component (the ``component`` reading of
``docs/algorithm.md``); an isolated robot reports 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DistributedLambda2", "MetropolisMixer", "metropolis_mix_one"]


def metropolis_weights(deg_a: np.ndarray, deg_b: np.ndarray) -> np.ndarray:
    """Metropolis weight of edge a <- b, ``1 / (1 + max(deg_a, deg_b))``."""
    return 1.0 / (1.0 + np.maximum(deg_a, deg_b))


def metropolis_mix_one(
    s: np.ndarray, degree: int, received: np.ndarray, degrees: np.ndarray
) -> np.ndarray:
    """One node's consensus round, ``s <- W_aa s + sum_b W_ab s_b`` (:class:`MetropolisMixer`
    for one robot's process).

    Parameters
    ----------
    s : ndarray
        This node's state.
    degree : int
        Its number of neighbours.
    received : ndarray, shape (K, *s.shape)
        The neighbours' states.
    degrees : ndarray, shape (K,)
        The neighbours' degrees.
    """
    w = metropolis_weights(float(degree), np.asarray(degrees, float)).reshape(
        (-1,) + (1,) * np.ndim(s)
    )
    return (1.0 - w.sum()) * s + (w * received).sum(axis=0)


class MetropolisMixer:
    """One round of average consensus on an undirected graph, Metropolis weights.

    ``W_ab = 1 / (1 + max(deg_a, deg_b))`` on edges, ``W_aa = 1 - sum_b W_ab``: doubly
    stochastic, so a round keeps the sum over each connected component (Xiao, Boyd & Lall
    2005). Shared by the distributed ``lambda2`` and the gauge sums (:mod:`resloc.cl.gauge`).

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
        Edges (each undirected edge once or in both directions; self-loops ignored).
    n : int
        Number of nodes.
    """

    def __init__(self, i: np.ndarray, j: np.ndarray, n: int) -> None:
        self.n = int(n)
        a = np.concatenate([i, j]).astype(np.int64)
        b = np.concatenate([j, i]).astype(np.int64)
        if a.size:
            key = np.unique(a * self.n + b)
            a, b = key // self.n, key % self.n
            keep = a != b
            a, b = a[keep], b[keep]
        self.a, self.b = a, b  # directed edges a <- b
        self.deg = np.bincount(a, minlength=self.n).astype(float)
        self.w = metropolis_weights(self.deg[a], self.deg[b])
        self.w_self = 1.0 - np.bincount(a, weights=self.w, minlength=self.n)

    @property
    def messages(self) -> int:
        """Directed messages per round (one per edge direction)."""
        return int(self.a.size)

    def laplacian(self, v: np.ndarray) -> np.ndarray:
        """``(L v)_a = deg_a v_a - sum_{b in N_a} v_b``, shape (n,)."""
        return self.deg * v - np.bincount(self.a, weights=v[self.b], minlength=self.n)

    def mix(self, s: np.ndarray) -> np.ndarray:
        """``W s`` for ``s`` of shape (n, ...)."""
        flat = s.reshape(self.n, -1)
        out = self.w_self[:, None] * flat
        contrib = self.w[:, None] * flat[self.b]
        for c in range(flat.shape[1]):
            out[:, c] += np.bincount(self.a, weights=contrib[:, c], minlength=self.n)
        return out.reshape(s.shape)


class DistributedLambda2:
    """Per-robot estimates of ``lambda2`` of the communication graph, updated every step.

    Parameters
    ----------
    n : int
        Number of robots (all teams of a batch; teams never share an edge).
    n_max : float or ndarray, shape (n,)
        Team size of each robot (an upper bound on ``lambda2``), equal within a team.
    rounds : int
        Neighbour exchanges per time step.
    leak : float
        Leak of the dynamic consensus in ``[0, 1)``.
    rng : numpy.random.Generator, optional
        Draws the initial ``y`` (uniform in ``[-1, 1]``) when ``y0`` is not given.
    y0 : ndarray, shape (n,), optional
        Initial ``y`` (e.g. drawn per team, so that a team's estimates do not depend on
        which other teams share the batch).
    """

    def __init__(
        self,
        n: int,
        n_max: float | np.ndarray,
        rounds: int = 3,
        leak: float = 0.01,
        rng: np.random.Generator | None = None,
        y0: np.ndarray | None = None,
    ) -> None:
        if rounds < 1:
            raise ValueError(f"rounds must be >= 1, got {rounds}")
        if not 0.0 <= leak < 1.0:
            raise ValueError(f"leak must be in [0, 1), got {leak}")
        rng = rng if rng is not None else np.random.default_rng(0)
        self.n = int(n)
        self.n_max = np.broadcast_to(np.asarray(n_max, dtype=float), (self.n,)).copy()
        self.rounds = int(rounds)
        self.leak = float(leak)
        self.y = (
            np.array(y0, dtype=float).reshape(self.n)
            if y0 is not None
            else rng.uniform(-1.0, 1.0, self.n)
        )
        self.s: np.ndarray | None = None  # (n, 3) consensus trackers
        self.phi: np.ndarray | None = None  # (n, 3) last local signals
        self.estimate = np.zeros(self.n)
        self.messages = 0  # neighbour messages sent so far (one per directed edge per round)
        # ... and per team: robot b is in team b // N when every team has N = n_max robots
        size = int(self.n_max[0]) if self.n else 1
        uniform = size >= 1 and self.n % size == 0 and bool(np.all(self.n_max == size))
        self.team_size = size if uniform else max(self.n, 1)
        self.messages_per_team = np.zeros(max(self.n // self.team_size, 1), np.int64)
        #: Steps run by the compiled twin (:mod:`resloc.cl.kernels_consensus`).
        self.compiled_steps = 0

    def step(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Run ``rounds`` exchanges on the graph with edges ``(i, j)``; return the estimates.

        Parameters
        ----------
        i, j : ndarray of int, shape (E,)
            Communication edges (each undirected edge once or in both directions).

        Returns
        -------
        ndarray, shape (n,)
            Each robot's estimate of its component's ``lambda2`` (0 when isolated).
        """
        # The compiled twin when the backend allows it (imported here: the kernels import
        # the CL registries, which import this module).
        from resloc.cl.kernels_consensus import compiled_lambda2_step

        compiled = compiled_lambda2_step(self, i, j)
        if compiled is not None:
            return compiled
        graph = MetropolisMixer(i, j, self.n)
        lap, mix, deg = graph.laplacian, graph.mix, graph.deg

        def signals(Ly: np.ndarray) -> np.ndarray:
            return np.stack([self.y, self.y * self.y, self.y * Ly], axis=1)

        k1, k2, k3 = self.n_max, 1.0, 2.0 * self.n_max
        eps = 0.05 / self.n_max
        if self.s is None:
            self.phi = signals(lap(self.y))
            self.s = self.phi.copy()
        for _ in range(self.rounds):
            Ly = lap(self.y)
            phi = signals(Ly)
            self.s = mix(self.s) + phi - self.phi + self.leak * (phi - self.s)
            self.phi = phi
            mean_y, mean_y2, mean_yly = self.s[:, 0], self.s[:, 1], self.s[:, 2]
            self.y = self.y - eps * (k1 * mean_y + k2 * Ly + k3 * (mean_y2 - 1.0) * self.y)
            var = mean_y2 - mean_y * mean_y
            with np.errstate(divide="ignore", invalid="ignore"):
                est = np.where(var > 1e-12, mean_yly / var, 0.0)
            est = np.where(np.isfinite(est), np.clip(est, 0.0, self.n_max), 0.0)
            self.estimate = np.where(deg > 0, est, 0.0)
        self.count_messages(graph.a)
        return self.estimate.copy()

    def count_messages(self, a: np.ndarray) -> None:
        """Count one step's exchanges: ``rounds`` messages on each directed edge ``a <- b``
        (``a``: the receivers, shape (M,)), in total and per team."""
        self.messages += self.rounds * int(a.size)
        teams = len(self.messages_per_team)
        self.messages_per_team += self.rounds * np.bincount(a // self.team_size, minlength=teams)
