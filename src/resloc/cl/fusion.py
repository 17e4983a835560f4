"""How robot i fuses neighbour j's estimate: naive (the paper), covariance intersection, split CI.

A relative update of robot i from ``z_ij`` uses robot j's transmitted estimate ``(x_j, P_j)``.
The joint density of ``[x_i; x_j]`` is needed for the predicted measurement, but the
cross-covariance ``P_ij`` is unknown to both robots: they have exchanged information before,
so their errors are correlated.

``naive`` (the paper, the default)
    Joint covariance ``blockdiag(P_i, P_j)``: the estimates are treated as independent. Fused
    again and again, the same information is counted many times and the covariances collapse
    (overconfidence: average NEES in the hundreds, ``docs/algorithm.md``).
``ci`` (covariance intersection; Julier & Uhlmann 1997, used for decentralized CL by
Carrillo-Arce, Nerurkar, Gordillo & Roumeliotis, IROS 2013)
    For any cross-covariance that makes the joint covariance valid,
    ``[[P_i, P_ij], [P_ji, P_j]] <= blockdiag(P_i / w, P_j / (1 - w))`` for every
    ``w in (0, 1)``. The update uses this bound as the joint covariance, so the posterior of
    ``x_i`` is consistent whatever ``P_ij`` is. ``w`` is chosen per link to minimise the
    trace (or determinant) of the posterior ``P_i``.
``split_ci`` (split covariance intersection; Julier & Uhlmann 2001, "General decentralized
data fusion with covariance intersection", used for CL by Li & Nashashibi 2013 and
Wanasinghe, Mann & Gosine 2014)
    Each covariance is kept as ``P = P_dep + P_ind``, where ``P_ind`` is the part of the error
    that no other robot's estimate can contain: initial error, process noise and measurement
    noise accumulated since the robot last transmitted its estimate. Only the dependent parts
    are inflated: ``blockdiag(P_dep,i / w + P_ind,i, P_dep,j / (1 - w) + P_ind,j)``. After the
    update the independent part is ``(I - K H_i) P_ind,i (I - K H_i)^T + K R K^T`` (j's
    independent error now also sits in i, which j still holds, so it moves to the dependent
    part), and a robot whose estimate was delivered to a neighbour turns all of its
    independent part into dependent.

Every function works on batches of links with a leading axis ``E``.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator
from typing import ClassVar

import numpy as np

from resloc.angles import wrap_angle
from resloc.filters.base import Moments
from resloc.filters.update import kalman_gain
from resloc.linalg import cholesky_jitter, forward_substitution, solve_spd, symmetrize
from resloc.models.measurement import range_bearing_jacobians
from resloc.models.motion import process_noise, unicycle_state_jacobian

__all__ = [
    "CI_GRID",
    "CICriterion",
    "FusionMethod",
    "ci_weights",
    "clip_independent",
    "fused_update",
    "propagate_independent",
]


class _RegisteredFusion(type):
    def __iter__(cls) -> Iterator[FusionMethod]:
        from resloc.cl.fusion_methods import FUSION_STRATEGIES

        return iter([cls(name) for name in FUSION_STRATEGIES])


class FusionMethod(str, metaclass=_RegisteredFusion):
    """The name of a fusion method: a key of :data:`~resloc.cl.fusion_methods.FUSION_STRATEGIES`
    (registering a strategy makes its name valid). Used like a string enum: ``FusionMethod("ci")``
    (``ValueError`` naming the registered methods), ``FusionMethod.CI``, ``.value``,
    ``list(FusionMethod)``; equal to its string, one object per name.
    """

    __slots__ = ()
    _interned: ClassVar[dict[str, FusionMethod]] = {}

    def __new__(cls, name: str) -> FusionMethod:
        from resloc.cl.fusion_methods import FUSION_STRATEGIES

        if name not in FUSION_STRATEGIES:
            raise ValueError(
                f"{name!r} is not a fusion method; registered: {', '.join(FUSION_STRATEGIES)}"
            )
        return cls._named(name)

    @classmethod
    def _named(cls, name: str) -> FusionMethod:
        if name not in cls._interned:
            cls._interned[name] = str.__new__(cls, name)
        return cls._interned[name]

    @property
    def value(self) -> str:
        """The name, as a plain string."""
        return str.__str__(self)

    def __repr__(self) -> str:
        return f"FusionMethod({self.value!r})"


# resloc's methods, by the names the code spells them with (``FusionMethod.GAUGE``).
for _name in ("naive", "ci", "split_ci", "tracked", "factorized", "gauge"):
    setattr(FusionMethod, _name.upper(), FusionMethod._named(_name))


class CICriterion(enum.StrEnum):
    """What the CI weight ``w`` minimises: the posterior ``trace(P_i)`` or ``det(P_i)``."""

    TRACE = "trace"
    DET = "det"


#: Candidate CI weights (the optimum is then refined by one parabolic step).
CI_GRID = np.linspace(0.02, 0.98, 33)


def _det2(a: np.ndarray) -> np.ndarray:
    return a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]


def _det3(a: np.ndarray) -> np.ndarray:
    return (
        a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
        - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
        + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0])
    )


def _posterior_cost(
    H_i: np.ndarray,
    H_j: np.ndarray,
    Pi_dep: np.ndarray,
    Pi_ind: np.ndarray | None,
    Pj_dep: np.ndarray,
    Pj_ind: np.ndarray | None,
    R: np.ndarray,
    w: np.ndarray,
    criterion: CICriterion,
) -> np.ndarray:
    """Linearized posterior ``trace`` / ``det`` of ``P_i`` for weights ``w: (G,) or (E, G)``.

    Returns an array of shape (E, G).

    Everything is reduced to 2 x 2 measurement-space quantities per link first, so the
    weights cost only element-wise arithmetic: with ``A = P_dep,i / w + P_ind,i``,
    ``C = A H_i^T`` and ``S = H_i A H_i^T + S_j``, ``S_j = H_j (P_dep,j / (1-w) + P_ind,j)
    H_j^T + R``: ``trace P = trace A - trace(C^T C S^{-1})`` and (determinant lemma)
    ``det P = det A det S_j / det S``.
    """
    HiT, HjT = np.swapaxes(H_i, -1, -2), np.swapaxes(H_j, -1, -2)
    zero3 = np.zeros_like(Pi_dep)
    Pii = zero3 if Pi_ind is None else Pi_ind
    Pji = zero3 if Pj_ind is None else Pj_ind
    Cd, Ci = Pi_dep @ HiT, Pii @ HiT  # (E, 3, 2)
    a_d, a_i = H_i @ Cd, H_i @ Ci  # (E, 2, 2)
    b_d, b_i = H_j @ Pj_dep @ HjT, H_j @ Pji @ HjT + R
    w = np.broadcast_to(w, (Pi_dep.shape[0], np.shape(w)[-1]))
    u = (1.0 / w)[:, :, None, None]
    v = (1.0 / (1.0 - w))[:, :, None, None]
    add = (slice(None), None)
    S_j = b_d[add] * v + b_i[add]  # (E, G, 2, 2)
    S = a_d[add] * u + a_i[add] + S_j
    if criterion is CICriterion.DET:
        A = Pi_dep[add] * u + Pii[add]
        return _det3(A) * _det2(S_j) / _det2(S)
    CtC_dd = np.swapaxes(Cd, -1, -2) @ Cd
    CtC_di = np.swapaxes(Cd, -1, -2) @ Ci
    CtC_ii = np.swapaxes(Ci, -1, -2) @ Ci
    G = CtC_dd[add] * u * u + (CtC_di + np.swapaxes(CtC_di, -1, -2))[add] * u + CtC_ii[add]
    det_s = _det2(S)
    # trace(G S^{-1}) with S^{-1} = adj(S) / det S.
    tr_gsinv = (
        G[..., 0, 0] * S[..., 1, 1]
        + G[..., 1, 1] * S[..., 0, 0]
        - G[..., 0, 1] * S[..., 1, 0]
        - G[..., 1, 0] * S[..., 0, 1]
    ) / det_s
    tr_a = (
        np.trace(Pi_dep, axis1=-2, axis2=-1)[:, None] * u[..., 0, 0]
        + np.trace(Pii, axis1=-2, axis2=-1)[:, None]
    )
    return tr_a - tr_gsinv


def ci_weights(
    x_i: np.ndarray,
    Pi_dep: np.ndarray,
    x_j: np.ndarray,
    Pj_dep: np.ndarray,
    R: np.ndarray,
    criterion: CICriterion = CICriterion.TRACE,
    Pi_ind: np.ndarray | None = None,
    Pj_ind: np.ndarray | None = None,
    grid: np.ndarray = CI_GRID,
) -> np.ndarray:
    """The CI weight ``w`` of each link: the minimiser of the posterior size of ``P_i``.

    The posterior ``P_i(w) = A - A H_i^T S^{-1} H_i A`` with ``A = P_dep,i / w + P_ind,i``,
    ``S = H_i A H_i^T + H_j (P_dep,j / (1 - w) + P_ind,j) H_j^T + R`` is evaluated with the
    range/bearing Jacobians at the means (eq. 3) on ``grid`` (vectorized over links and
    weights), and the best grid point is refined by one parabolic interpolation step. The
    filter's own moments are then computed with the chosen ``w`` (:func:`fused_update`).

    Parameters
    ----------
    x_i, x_j : ndarray, shape (E, 3)
    Pi_dep, Pj_dep : ndarray, shape (E, 3, 3)
        Covariances (``ci``) or their dependent parts (``split_ci``).
    R : ndarray, shape (2, 2)
    criterion : CICriterion
    Pi_ind, Pj_ind : ndarray, shape (E, 3, 3), optional
        Independent parts (``split_ci``).
    grid : ndarray, shape (G,)
        Candidate weights in ``(0, 1)``.

    Returns
    -------
    ndarray, shape (E,)
        1.0 where no weight of the grid makes the posterior smaller than the prior (then
        the link brings nothing under CI and is not fused).
    """
    criterion = CICriterion(criterion)
    H_i, H_j = range_bearing_jacobians(x_i, x_j)
    E = x_i.shape[0]
    cost = _posterior_cost(H_i, H_j, Pi_dep, Pi_ind, Pj_dep, Pj_ind, R, grid, criterion)
    k = np.argmin(cost, axis=1)
    rows = np.arange(E)
    best = cost[rows, k]
    kc = np.clip(k, 1, grid.size - 2)
    c0, c1, c2 = cost[rows, kc - 1], cost[rows, kc], cost[rows, kc + 1]
    h = grid[1] - grid[0]
    denom = c0 - 2.0 * c1 + c2
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(denom > 0.0, 0.5 * h * (c0 - c2) / denom, 0.0)
    w = np.where(k == kc, np.clip(grid[kc] + np.clip(shift, -h, h), grid[0], grid[-1]), grid[k])
    # Keep the refinement only where it helps (the cost is not exactly a parabola).
    refined = _posterior_cost(H_i, H_j, Pi_dep, Pi_ind, Pj_dep, Pj_ind, R, w[:, None], criterion)[
        :, 0
    ]
    better = refined <= best
    w = np.where(better, w, grid[k])
    best = np.where(better, refined, best)
    # w -> 1 is "ignore j" (posterior = prior): keep that when no grid weight beats it.
    P_prior = Pi_dep if Pi_ind is None else Pi_dep + Pi_ind
    prior = (
        _det3(P_prior) if criterion is CICriterion.DET else np.trace(P_prior, axis1=-2, axis2=-1)
    )
    return np.where(best < prior, w, 1.0)


def clip_independent(P: np.ndarray, P_ind: np.ndarray) -> np.ndarray:
    """Shrink ``P_ind`` where needed so that ``0 <= P_ind <= P`` (the dependent part is PSD).

    Exact arithmetic keeps ``P_ind <= P``; sigma-point moments and round-off can break it
    slightly. ``P_ind`` is scaled by ``1 / lambda_max(P^{-1} P_ind)`` where that exceeds 1.

    Parameters
    ----------
    P, P_ind : ndarray, shape (B, 3, 3)

    Returns
    -------
    ndarray, shape (B, 3, 3)
    """
    L = cholesky_jitter(P)
    eye = np.broadcast_to(np.eye(3), P.shape)
    Linv = forward_substitution(L, eye)
    M = symmetrize(Linv @ P_ind @ np.swapaxes(Linv, -1, -2))
    lam = np.linalg.eigvalsh(M)
    top = lam[:, -1]
    scale = np.where(top > 1.0, 1.0 / np.maximum(top, 1e-300), 1.0)
    out = P_ind * scale[:, None, None]
    neg = lam[:, 0] < 0.0
    if neg.any():  # project the independent part itself onto the PSD cone
        w, V = np.linalg.eigh(symmetrize(out[neg]))
        out[neg] = np.einsum("bij,bj,bkj->bik", V, np.maximum(w, 0.0), V)
    return symmetrize(out)


def fused_update(
    x_i: np.ndarray,
    P_i: np.ndarray,
    x_j: np.ndarray,
    P_j: np.ndarray,
    nu: np.ndarray,
    m: Moments,
    R: np.ndarray,
    method: FusionMethod,
    criterion: CICriterion = CICriterion.TRACE,
    Pi_ind: np.ndarray | None = None,
    Pj_ind: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Kalman update of ``x_i`` from ``z_ij`` and j's estimate with a consistent joint bound.

    ``ci``: joint ``blockdiag(P_i / w, P_j / (1 - w))``; ``split_ci``:
    ``blockdiag(P_dep,i / w + P_ind,i, P_dep,j / (1 - w) + P_ind,j)``. Both are the naive
    joint plus inflations ``D_i = P_dep,i (1/w - 1)`` and ``D_j = P_dep,j (1/(1-w) - 1)``. The
    filter's own moments ``m`` of the naive joint (CKF/UKF points or EKF linearization) are
    extended by the inflations through the range/bearing Jacobians at the means:
    ``S = S_naive + H_i D_i H_i^T + H_j D_j H_j^T``, ``P^xz = P^xz_naive + D_i H_i^T``, prior
    ``A = P_i + D_i``; then ``K = P^xz S^{-1}``, ``x_i += K Lambda``, ``P_i = A - K S K^T``
    (Joseph form for the EKF). For the EKF this is exactly the update with the bound as the
    joint covariance; for the sigma-point filters the points keep the spread of the actual
    uncertainties (pushing points drawn from a 10-50 times inflated ``P_j`` through the
    range/bearing model puts them on top of the observer and breaks the moments).

    Parameters
    ----------
    x_i, x_j : ndarray, shape (E, 3)
    P_i, P_j : ndarray, shape (E, 3, 3)
        Full covariances.
    nu : ndarray, shape (E, 2)
        Innovations ``z - hat z`` of the naive moments.
    m : Moments
        The filter's moments of ``z_ij`` under ``blockdiag(P_i, P_j)`` (same rows).
    R : ndarray, shape (2, 2)
    method : FusionMethod
        ``ci`` or ``split_ci`` (``naive`` is the plain update of :mod:`resloc.cl.step`).
    criterion : CICriterion
    Pi_ind, Pj_ind : ndarray, shape (E, 3, 3), optional
        Independent parts (required by ``split_ci``).

    Returns
    -------
    x, P : ndarray, shapes (E, 3), (E, 3, 3)
        Posterior of robot i.
    P_ind : ndarray, shape (E, 3, 3) or None
        Posterior independent part (``split_ci``), else None.
    w : ndarray, shape (E,)
        The CI weights used.
    """
    method = FusionMethod(method)
    if method is FusionMethod.NAIVE:
        raise ValueError("fused_update is for ci / split_ci; naive uses kalman_update")
    split = method is FusionMethod.SPLIT_CI
    if split and (Pi_ind is None or Pj_ind is None):
        raise ValueError("split_ci needs the independent parts of both covariances")
    if split:
        Pi_ind = clip_independent(P_i, Pi_ind)
        Pj_ind = clip_independent(P_j, Pj_ind)
        Pi_dep, Pj_dep = P_i - Pi_ind, P_j - Pj_ind
    else:
        Pi_dep, Pj_dep, Pi_ind, Pj_ind = P_i, P_j, None, None
    w_all = ci_weights(x_i, Pi_dep, x_j, Pj_dep, R, criterion, Pi_ind, Pj_ind)
    use = w_all < 1.0  # w = 1: j adds nothing; the prior is kept
    w = np.where(use, w_all, 0.5)
    H_i, H_j = range_bearing_jacobians(x_i, x_j)
    D_i = Pi_dep * (1.0 / w - 1.0)[:, None, None]
    D_j = Pj_dep * (1.0 / (1.0 - w) - 1.0)[:, None, None]
    HiT, HjT = np.swapaxes(H_i, -1, -2), np.swapaxes(H_j, -1, -2)
    A = symmetrize(P_i + D_i)
    extra_j = H_j @ D_j @ HjT
    S = symmetrize(m.S + H_i @ D_i @ HiT + extra_j)
    Pxz = m.Pxz + D_i @ HiT
    K = kalman_gain(S, Pxz)
    x_new = x_i + np.einsum("eij,ej->ei", K, nu)
    x_new[:, 2] = wrap_angle(x_new[:, 2])
    if m.H_i is not None and m.R_eff is not None:  # EKF: Joseph form
        IKH = np.eye(3) - K @ m.H_i
        R_eff = m.R_eff + extra_j
        P_new = IKH @ A @ np.swapaxes(IKH, -1, -2) + K @ R_eff @ np.swapaxes(K, -1, -2)
    else:
        P_new = A - K @ S @ np.swapaxes(K, -1, -2)
    P_new = symmetrize(P_new)
    keep = ~use
    x_new[keep], P_new[keep] = x_i[keep], P_i[keep]
    if not split:
        return x_new, P_new, None, w_all
    # Statistical linearization of the observer's block: P^xz = A H^T.
    H_eff = m.H_i if m.H_i is not None else np.swapaxes(solve_spd(A, Pxz), -1, -2)
    IKH = np.eye(3) - K @ H_eff
    P_ind_new = IKH @ Pi_ind @ np.swapaxes(IKH, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    P_ind_new[keep] = Pi_ind[keep]
    return x_new, P_new, clip_independent(P_new, symmetrize(P_ind_new)), w_all


def propagate_independent(
    x: np.ndarray,
    P_ind: np.ndarray,
    u: np.ndarray,
    dt: float,
    odometry_std: np.ndarray,
    floor_std: np.ndarray,
) -> np.ndarray:
    """Time update of the independent part: ``F P_ind F^T + Q`` (eqs. 1-2, linearized).

    The process noise is fresh, so it is independent of every other robot's estimate.

    Parameters
    ----------
    x : ndarray, shape (B, 3)
        Estimates *before* the prediction (the Jacobian's linearization point).
    P_ind : ndarray, shape (B, 3, 3)
    u : ndarray, shape (B, 2)
        Measured odometry.
    dt : float
    odometry_std : ndarray, shape (2,)
    floor_std : ndarray, shape (3,)

    Returns
    -------
    ndarray, shape (B, 3, 3)
    """
    F = unicycle_state_jacobian(x, u, dt)
    Q = process_noise(x, dt, np.asarray(odometry_std), np.asarray(floor_std))
    return symmetrize(F @ P_ind @ np.swapaxes(F, -1, -2) + Q)
