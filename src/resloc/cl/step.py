"""One cooperative-localization step of a batch of robots (Algorithm 1).

``predict`` then ``correct``. Both are pure functions of arrays with a leading batch axis;
a robot process calls them with batch size 1, the simulator with every robot of every trial.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from resloc.cl.cusum import link_cusum, link_mean_cusum, whiten
from resloc.cl.cusum import nis as normalized_innovation_squared
from resloc.cl.detector import InnovationNorm, attack_detected, innovation_norm
from resloc.cl.fusion import FusionMethod, fuse_links
from resloc.cl.kernels import fast_correct
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.cl.trigger import event_threshold, event_triggered
from resloc.filters.base import GaussianFilter, Moments
from resloc.filters.update import covariance_is_pd, innovation, kalman_update, repair_covariance
from resloc.models.motion import process_noise

__all__ = ["LinkBatch", "LinkOutcome", "correct", "predict"]


def predict(
    filt: GaussianFilter,
    x: np.ndarray,
    P: np.ndarray,
    u: np.ndarray,
    dt: float,
    params: CLParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Time update of every robot from its measured odometry (Algorithm 1, "Prediction").

    Parameters
    ----------
    filt : GaussianFilter
    x : ndarray, shape (B, 3)
    P : ndarray, shape (B, 3, 3)
    u : ndarray, shape (B, 2)
        Measured ``(v, omega)``.
    dt : float
    params : CLParams

    Returns
    -------
    x, P : ndarray, shapes (B, 3), (B, 3, 3)
    """
    Q = process_noise(x, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std))
    return filt.predict(x, P, u, dt, Q)


@dataclass
class LinkBatch:
    """The relative measurements of one step, one row per directed link ``(i, j)``.

    Rows must be sorted by ``i`` (then by ``j``: the sequential update order).

    Attributes
    ----------
    i : ndarray of int, shape (E,)
        Observer, as an index into the batch ``[0, B)``.
    j : ndarray of int, shape (E,)
        Observed robot's id (used only as a key of the per-link memory).
    z : ndarray, shape (E, 2)
        Measured ``[range, bearing]`` (possibly falsified).
    x_nb : ndarray, shape (E, 3)
        Neighbour j's current predicted estimate: what a transmission would carry.
    P_nb : ndarray, shape (E, 3, 3)
    channel_ok : ndarray of bool, shape (E,)
        Whether a transmission on this link would get through (False in a jammed CDZ).
    risk_s, risk_c : ndarray, shape (B,)
        ``Ds(i)``, ``Dc(i)`` for every robot of the batch.
    lambda2 : ndarray, shape (B,)
        Algebraic connectivity seen by every robot of the batch.
    tamper : callable ``(rows, z_hat, S) -> z``, optional
        Issue 6: an adversary that sees robot i's predicted measurement ``(len(rows), 2)``
        and innovation covariance ``(len(rows), 2, 2)`` of ``rows`` and returns the
        measurements i receives there (the stealthy attacker of
        :mod:`resloc.world.adversary`, supplied by the simulator). None: ``z`` as is.
    P_nb_ind : ndarray, shape (E, 3, 3), optional
        Independent part of ``P_nb`` (split covariance intersection, transmitted with it).
    """

    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    x_nb: np.ndarray
    P_nb: np.ndarray
    channel_ok: np.ndarray
    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    tamper: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None
    P_nb_ind: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.i)


@dataclass
class LinkOutcome:
    """What happened on every link of a :class:`LinkBatch`.

    Attributes
    ----------
    norm : ndarray, shape (E,)
        Trigger-norm of the innovation ``||Lambda_ij||`` (eq. 9).
    threshold : ndarray, shape (E,)
        ``delta_ij`` of eq. (11) (``nan`` where the detector discarded the link first).
    detected : ndarray of bool, shape (E,)
        Discarded by the attack detector.
    triggered : ndarray of bool, shape (E,)
        A transmission was attempted (eq. 10).
    delivered : ndarray of bool, shape (E,)
        The transmission got through (``sigma_ij = 1``).
    fused : ndarray of bool, shape (E,)
        ``z_ij`` was used in a Kalman update.
    repaired : ndarray of bool, shape (E,)
        The observer's covariance had to be projected back to positive definite after this
        link's update (``summed`` updates: on the robot's first fused link).
    """

    norm: np.ndarray
    threshold: np.ndarray
    detected: np.ndarray
    triggered: np.ndarray
    delivered: np.ndarray
    fused: np.ndarray
    repaired: np.ndarray

    @property
    def repairs(self) -> int:
        """Covariances that had to be projected back to positive definite."""
        return int(np.count_nonzero(self.repaired))

    @classmethod
    def empty(cls, E: int) -> LinkOutcome:
        return cls(np.full(E, np.nan), np.full(E, np.nan), *np.zeros((5, E), dtype=bool))


def _at(v: float | np.ndarray, idx: np.ndarray) -> float | np.ndarray:
    """A scalar parameter as is, or a per-robot parameter ``(B,)`` gathered at ``idx``."""
    a = np.asarray(v, dtype=float)
    return a if a.ndim == 0 else a[idx]


def _take(m: Moments, rows: np.ndarray) -> Moments:
    return Moments(
        m.z_hat[rows],
        m.S[rows],
        m.Pxz[rows],
        None if m.H_i is None else m.H_i[rows],
        None if m.R_eff is None else m.R_eff[rows],
    )


def _decide(
    filt: GaussianFilter,
    x_i: np.ndarray,
    P_i: np.ndarray,
    rows: np.ndarray,
    links: LinkBatch,
    params: CLParams,
    memory: LinkMemory | None,
    out: LinkOutcome,
) -> tuple[np.ndarray, Moments, np.ndarray]:
    """Detector, trigger and channel for ``rows`` of ``links`` given robot estimates ``x_i``.

    Returns the rows to fuse, the moments to fuse them with (same order as ``rows``) and
    the innovations. Writes the per-link decisions into ``out``.
    """
    ii = links.i[rows]
    R = params.R
    x_ref, P_ref = links.x_nb[rows], links.P_nb[rows]
    cached = params.neighbour_estimate is NeighbourEstimate.CACHED
    need_memory = cached or params.threshold_innovation is ThresholdInnovation.LAST_SENT
    if need_memory and memory is None:
        raise ValueError("cached neighbour estimates / last_sent threshold need a LinkMemory")
    known = np.ones(len(rows), dtype=bool)
    pos = np.zeros(len(rows), dtype=int)
    if need_memory:
        known, pos = memory.lookup(ii, links.j[rows])
    if cached:
        x_ref = np.where(known[:, None], memory.x[pos] if len(memory) else x_ref, x_ref)
        P_ref = np.where(known[:, None, None], memory.P[pos] if len(memory) else P_ref, P_ref)
    if params.fusion.tracks_cross:  # issue 6: tracked / factorized cross-covariances
        m = _joint(memory).moments(filt, x_i, P_i, x_ref, P_ref, ii, links.j[rows], R)
    else:
        m = filt.relative_moments(x_i, P_i, x_ref, P_ref, R)
    z_rows = links.z[rows] if links.tamper is None else links.tamper(rows, m.z_hat, m.S)
    nu = innovation(z_rows, m.z_hat)
    n_trig = innovation_norm(nu, m.S, params.trigger_norm, params.noise_std)
    if params.detector_norm == params.trigger_norm:
        n_det = n_trig
    else:
        n_det = innovation_norm(nu, m.S, params.detector_norm, params.noise_std)
    gated = (
        attack_detected(n_det, _at(params.rho, ii))
        if params.detector
        else np.zeros(len(rows), bool)
    )
    detected = gated
    if params.cusum:
        detected = detected | _cusum_alarm(nu, m.S, n_det, ii, links.j[rows], params, memory)
    if params.mean_cusum:
        if memory is None:
            raise ValueError("detector mean CUSUM (params.mean_cusum) needs a LinkMemory")
        detected = detected | link_mean_cusum(
            memory.mean_cusum,
            ii,
            links.j[rows],
            whiten(nu, m.S),
            _at(params.mean_cusum_k, ii),
            _at(params.mean_cusum_h, ii),
            ~gated,
        )
    accepted = ~detected
    if params.threshold_innovation is ThresholdInnovation.LAST_SENT:
        size = np.where(known, memory.last_norm[pos] if len(memory) else 0.0, 0.0)
    else:
        size = n_trig
    delta = event_threshold(
        _at(params.alpha, ii),
        links.lambda2[ii],
        _at(params.gamma, ii),
        size,
        _at(params.zeta_s, ii),
        links.risk_s[ii],
        _at(params.zeta_c, ii),
        links.risk_c[ii],
        params.risk_factor_floor,
    )
    if params.trigger:
        fire = event_triggered(n_trig, delta)
        if cached:
            fire |= ~known  # nothing to compare against before the first reception
    else:
        fire = np.ones(len(rows), bool)
    triggered = accepted & fire
    delivered = triggered & links.channel_ok[rows]
    fuse = delivered.copy()
    if cached and params.update_without_transmission:
        fuse |= accepted & ~triggered & known

    out.norm[rows] = n_trig
    out.threshold[rows] = np.where(accepted, delta, np.nan)
    out.detected[rows] = detected
    out.triggered[rows] = triggered
    out.delivered[rows] = delivered
    out.fused[rows] = fuse

    if need_memory and delivered.any():
        d = rows[delivered]
        memory.store(links.i[d], links.j[d], links.x_nb[d], links.P_nb[d], n_trig[delivered])
    if cached and delivered.any():
        # A delivered message carries j's current estimate: fuse with that, not the cache.
        sub = np.flatnonzero(delivered)
        fresh = filt.relative_moments(
            x_i[sub], P_i[sub], links.x_nb[rows[sub]], links.P_nb[rows[sub]], R
        )
        m = Moments(
            m.z_hat.copy(),
            m.S.copy(),
            m.Pxz.copy(),
            None if m.H_i is None else m.H_i.copy(),
            None if m.R_eff is None else m.R_eff.copy(),
        )
        m.z_hat[sub], m.S[sub], m.Pxz[sub] = fresh.z_hat, fresh.S, fresh.Pxz
        if m.H_i is not None:
            m.H_i[sub], m.R_eff[sub] = fresh.H_i, fresh.R_eff
        nu[sub] = innovation(z_rows[sub], fresh.z_hat)
    return fuse, m, nu


def _cusum_alarm(nu, S, n_det, ii, jj, params: CLParams, memory: LinkMemory | None):
    """Issue 6: per-link CUSUM of the NIS (:mod:`resloc.cl.cusum`), state in ``memory``."""
    if memory is None:
        raise ValueError("detector CUSUM (params.cusum) needs a LinkMemory")
    if params.detector_norm is InnovationNorm.NIS:
        stat = n_det * n_det
    else:
        stat = normalized_innovation_squared(nu, S)
    k = _at(params.cusum_k, ii)
    alarm = link_cusum(memory.cusum, ii, jj, stat, k, _at(params.cusum_h, ii), params.cusum_cap)
    # While a link's CUSUM alarms, its gate tightens to the CUSUM reference: measurements
    # whose own NIS is above k are discarded, honest-looking ones still pass.
    return alarm & (stat > k)


def _joint(memory: LinkMemory | None):
    """Issue 6: the bookkeeping of ``tracked`` / ``factorized`` / ``gauge`` fusion."""
    if memory is None or memory.joint is None:
        raise ValueError(
            "fusion 'tracked' / 'factorized' / 'gauge' needs memory.joint "
            "(a JointCovariance / FactorizedCovariance / GaugeCovariance)"
        )
    return memory.joint


def _reference_only(params: CLParams, links: LinkBatch) -> bool:
    """Issue-6 options the compiled fast path does not implement (run the reference)."""
    return (
        params.fusion is not FusionMethod.NAIVE
        or params.cusum
        or params.mean_cusum
        or links.tamper is not None
    )


def _ensure_pd(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P: (B, 3, 3)`` with its non-positive-definite members repaired, and which they were."""
    bad = ~covariance_is_pd(P)
    if bad.any():
        P = P.copy()
        P[bad] = repair_covariance(P[bad])
    return P, bad


def correct(
    filt: GaussianFilter,
    x: np.ndarray,
    P: np.ndarray,
    links: LinkBatch,
    params: CLParams,
    memory: LinkMemory | None = None,
) -> tuple[np.ndarray, np.ndarray, LinkOutcome]:
    """Measurement correction of every robot from its neighbours (Algorithm 1, "Correction").

    For each link: predicted measurement from the joint points over ``[x_i; x_j]``,
    innovation (eq. 9), attack detection (discard when ``||Lambda|| > rho``), adaptive
    threshold (eq. 11), event condition (eq. 10), transmission through the channel
    (eq. 8: no update when ``sigma_ij = 0``), and the Kalman update of ``x_i`` only.

    Parameters
    ----------
    filt : GaussianFilter
    x : ndarray, shape (B, 3)
        Predicted estimates ``hat x_i,k|k-1``.
    P : ndarray, shape (B, 3, 3)
    links : LinkBatch
        Sorted by observer ``i``.
    params : CLParams
    memory : LinkMemory, optional
        Needed for ``cached`` neighbour estimates and the ``last_sent`` threshold; updated
        in place.

    Returns
    -------
    x, P : ndarray, shapes (B, 3), (B, 3, 3)
        Corrected estimates ``hat x_i,k|k``, ``P_i,k|k``.
    outcome : LinkOutcome
    """
    E = len(links)
    if E == 0:
        return x, P, LinkOutcome.empty(E)
    # Compiled path (numba) when it covers the filter and the options; else the reference.
    fast = (
        None if _reference_only(params, links) else fast_correct(filt, x, P, links, params, memory)
    )
    if fast is not None:
        out = LinkOutcome(
            fast.norm,
            fast.threshold,
            fast.detected,
            fast.triggered,
            fast.delivered,
            fast.fused,
            fast.repaired,
        )
        return fast.x, fast.P, out
    out = LinkOutcome.empty(E)
    x = x.copy()
    P = P.copy()
    if params.fusion is not FusionMethod.NAIVE and (
        params.update_mode is UpdateMode.SUMMED or params.update_without_transmission
    ):
        raise ValueError(
            f"fusion {params.fusion.value!r} needs sequential updates of transmitted estimates"
        )
    if params.update_mode is UpdateMode.SUMMED:
        rows = np.arange(E)
        fuse, m, nu = _decide(filt, x[links.i], P[links.i], rows, links, params, memory, out)
        f = np.flatnonzero(fuse)
        if f.size:
            ii = links.i[f]
            mf = _take(m, f)
            Pi = P[ii]
            x_upd, P_upd = kalman_update(x[ii], Pi, nu[f], mf)
            np.add.at(x, ii, x_upd - x[ii])
            np.add.at(P, ii, P_upd - Pi)
            from resloc.angles import wrap_angle

            x[:, 2] = wrap_angle(x[:, 2])
            # One repair per robot, not per link (ii repeats a robot with several links).
            touched, first = np.unique(ii, return_index=True)
            Pt = P[touched]
            P[touched], bad = _ensure_pd(0.5 * (Pt + np.swapaxes(Pt, -1, -2)))
            out.repaired[f[first[bad]]] = True
        return x, P, out

    start = np.searchsorted(links.i, links.i, side="left")
    rank = np.arange(E) - start
    order = np.argsort(rank, kind="stable")
    bounds = np.searchsorted(rank[order], np.arange(int(rank.max()) + 2))
    for r in range(len(bounds) - 1):
        rows = order[bounds[r] : bounds[r + 1]]
        ii = links.i[rows]  # distinct within a round
        fuse, m, nu = _decide(filt, x[ii], P[ii], rows, links, params, memory, out)
        if not fuse.any():
            continue
        f = np.flatnonzero(fuse)
        if params.fusion is FusionMethod.NAIVE or params.fusion.bookkeeping:
            x_new, P_new = kalman_update(x[ii[f]], P[ii[f]], nu[f], _take(m, f))
            if params.fusion.bookkeeping:  # record the update (cross-covariances / gauge)
                P_new = _joint(memory).update(
                    ii[f],
                    links.j[rows[f]],
                    x[ii[f]],
                    links.x_nb[rows[f]],
                    _take(m, f),
                    params.R,
                    P_new,
                )
        else:  # issue 6: covariance intersection (resloc.cl.fusion)
            rf = rows[f]
            x_new, P_new = fuse_links(
                x[ii[f]],
                P[ii[f]],
                ii[f],
                links.x_nb[rf],
                links.P_nb[rf],
                None if links.P_nb_ind is None else links.P_nb_ind[rf],
                nu[f],
                _take(m, f),
                params.R,
                params.fusion,
                params.ci_criterion,
                memory,
            )
        P_new, bad = _ensure_pd(P_new)
        out.repaired[rows[f[bad]]] = True
        x[ii[f]] = x_new
        P[ii[f]] = P_new
    if params.fusion.bookkeeping:
        P = _joint(memory).finish(P)  # resloc.cl.tracking / .factorized / .gauge
    if params.fusion is FusionMethod.SPLIT_CI and out.delivered.any():
        # Issue 6, split CI: a delivered estimate is now held by a neighbour too, so its
        # sender's independent part becomes dependent.
        memory.independent[links.j[out.delivered]] = 0.0
    return x, P, out
