"""Adversaries beyond additive draws: the detector-aware stealthy attacker and replay.

**Stealthy** (the paper's adversary "maximizes ``||r_ij||`` ... while avoiding detection",
eq. 5 and the text after it). The attacker knows robot i's predicted measurement
``hat z_ij`` and innovation covariance ``S`` (the victim filter's) and the detector it runs.
It injects ``Gamma = a d`` along a fixed unit direction ``d`` (default: range, which
distorts the inter-robot distances the MSLE measures; a constant sign makes the bias
persistent), with the largest ``a >= 0`` such that every test stays at
``margin`` of its threshold:

* a norm gate ``||Lambda + a d||_W <= margin rho`` with ``W = I`` (``euclidean``),
  ``diag(1/sigma^2)`` (``scaled``) or ``S^{-1}`` (``nis``);
* with ``knowledge = full`` and a CUSUM on the NIS, also ``NIS <= margin k`` (the CUSUM's
  reference: any mean NIS above ``k`` raises the alarm eventually);
* with ``knowledge = full`` and the mean-shift CUSUM, also ``|w_c| <= margin k_m`` for both
  components of the whitened innovation ``w = L^{-1} (Lambda + a d)`` (linear in ``a``).

Each constraint is a quadratic ``a^2 d'Wd + 2 a d'W Lambda + Lambda'W Lambda - c^2 <= 0``;
``a`` is the smallest of their largest roots (0 when the honest measurement already fails a
test), and at most what the attacker can physically inject (``|a d_k| <= bias_k``).

**Replay**: the measurement of the same directed link recorded ``delay`` steps earlier
(honest then) replaces the current one.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np

from resloc.cl.cusum import whiten
from resloc.cl.detector import InnovationNorm
from resloc.cl.kernels_detection import NORM_CODE
from resloc.cl.kernels_tamper import kernel_tamper
from resloc.linalg import solve_spd
from resloc.world.attacks import StealthKnowledge, apply_injection

__all__ = [
    "ReplayBuffer",
    "StealthKnowledge",
    "largest_linear_step",
    "largest_stealthy_step",
    "stealthy_tamper",
]


def largest_stealthy_step(
    nu: np.ndarray, d: np.ndarray, W: np.ndarray, c2: np.ndarray
) -> np.ndarray:
    """Largest ``a >= 0`` with ``(nu + a d)^T W (nu + a d) <= c2``, per row.

    Parameters
    ----------
    nu : ndarray, shape (E, 2)
        Honest innovations ``z - hat z``.
    d : ndarray, shape (2,)
        Injection direction.
    W : ndarray, shape (E, 2, 2)
        Metric of the test (symmetric positive definite).
    c2 : ndarray, shape (E,)
        Squared bound of the statistic.

    Returns
    -------
    ndarray, shape (E,)
        0 where the honest innovation already violates the bound.
    """
    Wd = W @ d  # (E, 2)
    qa = Wd @ d
    qb = np.einsum("ei,ei->e", Wd, nu)
    qc = np.einsum("ei,eij,ej->e", nu, W, nu) - c2
    disc = qb * qb - qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        root = (-qb + np.sqrt(np.maximum(disc, 0.0))) / qa
    ok = (qc <= 0.0) & (qa > 0.0)
    return np.where(ok, np.maximum(root, 0.0), 0.0)


def largest_linear_step(w0: np.ndarray, v: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Largest ``a >= 0`` with ``|w0_k + a v_k| <= c`` for every component k, per row.

    Parameters
    ----------
    w0 : ndarray, shape (E, n)
        Honest whitened innovations.
    v : ndarray, shape (E, n)
        Whitened injection direction.
    c : ndarray, shape (E,)
        Bound.

    Returns
    -------
    ndarray, shape (E,)
        0 where the honest value already violates a bound.
    """
    c = np.asarray(c, dtype=float)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        hi = np.where(v > 0, (c - w0) / v, np.where(v < 0, (-c - w0) / v, np.inf))
    ok = (np.abs(w0) <= c).all(axis=1)
    return np.where(ok, np.maximum(hi.min(axis=1), 0.0), 0.0)


def _metric(kind: InnovationNorm, S: np.ndarray, noise_std: np.ndarray) -> np.ndarray:
    E = S.shape[0]
    if kind is InnovationNorm.EUCLIDEAN:
        return np.broadcast_to(np.eye(2), (E, 2, 2))
    if kind is InnovationNorm.SCALED:
        return np.broadcast_to(np.diag(1.0 / np.asarray(noise_std, float) ** 2), (E, 2, 2))
    return solve_spd(S, np.broadcast_to(np.eye(2), (E, 2, 2)).copy())


def stealthy_tamper(
    z: np.ndarray,
    attacked: np.ndarray,
    observer: np.ndarray,
    direction: np.ndarray,
    margin: float,
    bias: np.ndarray,
    detector: bool,
    norm: InnovationNorm,
    rho: float | np.ndarray,
    noise_std: np.ndarray,
    cusum_k: float | np.ndarray | None = None,
    knowledge: StealthKnowledge = StealthKnowledge.FULL,
    mean_cusum_k: float | np.ndarray | None = None,
) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """The stealthy attacker of one step against one victim estimator, as a ``tamper`` hook.

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Honest measurements of the step (one row per link of the step's ``LinkBatch``).
    attacked : ndarray of bool, shape (E,)
        Links the attacker controls this step (drawn by the world).
    observer : ndarray of int, shape (E,)
        Robot i of each link (indexes per-robot ``rho`` / ``cusum_k``).
    direction : ndarray, shape (2,)
        Injection direction (normalized here).
    margin : float
        Fraction of each threshold the statistic is driven to.
    bias : ndarray, shape (2,)
        Largest injectable magnitude per component.
    detector : bool
        Whether the victim runs the gate (off: only ``bias`` bounds the attack).
    norm : InnovationNorm
        The victim's detector norm.
    rho : float or ndarray, shape (B,)
        The victim's gate threshold (per robot).
    noise_std : ndarray, shape (2,)
        Range / bearing noise std (for the ``scaled`` norm).
    cusum_k : float or ndarray, shape (B,), optional
        The victim's CUSUM reference (None: no CUSUM).
    knowledge : StealthKnowledge
    mean_cusum_k : float or ndarray, shape (B,), optional
        The victim's mean-shift CUSUM reference (None: no such test).

    Returns
    -------
    callable ``tamper(rows, z_hat, S) -> z_rows``
        Given link rows (indices into the step's links) with the victim's predicted
        measurements ``(len(rows), 2)`` and innovation covariances ``(len(rows), 2, 2)``,
        returns the measurements robot i receives on those rows. Its attribute
        ``kernel_form`` (:class:`~resloc.cl.kernels_tamper.KernelTamper`) describes the same
        attacker to the compiled CL kernel.
    """
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    bias = np.asarray(bias, dtype=float)
    with np.errstate(divide="ignore"):
        cap = float(np.min(np.where(np.abs(d) > 0, bias / np.abs(d), np.inf)))
    norm = InnovationNorm(norm)
    knowledge = StealthKnowledge(knowledge)

    def per_robot(v, idx):
        a = np.asarray(v, dtype=float)
        return np.broadcast_to(a, idx.shape) if a.ndim == 0 else a[idx]

    def tamper(rows: np.ndarray, z_hat: np.ndarray, S: np.ndarray) -> np.ndarray:
        out = z[rows].copy()
        hit = attacked[rows]
        if not hit.any():
            return out
        h = np.flatnonzero(hit)
        zr = out[h]
        nu = zr - z_hat[h]
        nu[:, 1] = np.mod(nu[:, 1] + np.pi, 2.0 * np.pi) - np.pi
        obs = observer[rows[h]]
        a = np.full(h.size, cap)
        if detector:
            W = _metric(norm, S[h], noise_std)
            c = margin * per_robot(rho, obs)
            a = np.minimum(a, largest_stealthy_step(nu, d, W, c * c))
        if cusum_k is not None and knowledge is StealthKnowledge.FULL:
            W = _metric(InnovationNorm.NIS, S[h], noise_std)
            a = np.minimum(a, largest_stealthy_step(nu, d, W, margin * per_robot(cusum_k, obs)))
        if mean_cusum_k is not None and knowledge is StealthKnowledge.FULL:
            Sh = S[h]
            w0 = whiten(nu, Sh)
            v = whiten(np.broadcast_to(d, nu.shape).copy(), Sh)
            a = np.minimum(a, largest_linear_step(w0, v, margin * per_robot(mean_cusum_k, obs)))
        a = np.where(np.isfinite(a), a, 0.0)
        out[h] = apply_injection(zr, a[:, None] * d[None, :])
        return out

    # The same attacker as plain data: the compiled CL kernel computes it in its link loop.
    full = knowledge is StealthKnowledge.FULL
    tamper.kernel_form = kernel_tamper(
        z, attacked, observer, d, margin, cap, detector, NORM_CODE[norm], rho, noise_std,
        cusum_k if full else None, mean_cusum_k if full else None,
    )  # fmt: skip
    return tamper


class ReplayBuffer:
    """The honest measurements of the last ``delay`` steps, keyed by directed link.

    Parameters
    ----------
    delay : int
        How many steps back a replayed measurement comes from.
    n_nodes : int
        Size of the robot id space (keys are ``i * n_nodes + j``).
    """

    def __init__(self, delay: int, n_nodes: int) -> None:
        if delay < 1:
            raise ValueError(f"replay delay must be >= 1 step, got {delay}")
        self.delay = int(delay)
        self.n_nodes = int(n_nodes)
        self._hist: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.delay)

    def replayed(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The measurements of links ``(i, j)`` recorded ``delay`` steps ago.

        Returns
        -------
        found : ndarray of bool, shape (E,)
            The link existed then.
        z : ndarray, shape (E, 2)
            Its measurement then (valid where ``found``).
        """
        E = len(i)
        if len(self._hist) < self.delay:
            return np.zeros(E, dtype=bool), np.zeros((E, 2))
        keys, zs = self._hist[0]
        k = np.asarray(i, np.int64) * self.n_nodes + np.asarray(j, np.int64)
        if not len(keys):
            return np.zeros(E, dtype=bool), np.zeros((E, 2))
        pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        found = keys[pos] == k
        return found, zs[pos]

    def record(self, i: np.ndarray, j: np.ndarray, z: np.ndarray) -> None:
        """Append this step's honest measurements (the oldest step drops out)."""
        k = np.asarray(i, np.int64) * self.n_nodes + np.asarray(j, np.int64)
        order = np.argsort(k, kind="stable")
        self._hist.append((k[order], np.asarray(z, float)[order].copy()))
