"""One cooperative-localization step of a batch of robots (Algorithm 1).

``predict`` then ``correct``. Both are pure functions of arrays with a leading batch axis;
a robot process calls them with batch size 1, the simulator with every robot of every trial.
Their compiled twins (:mod:`resloc.cl.kernels`, :mod:`resloc.cl.kernels_predict`) are
imported on the first call: importing numba takes about half a second, which a command
that never steps an estimator (``--help``, a rejected argument) should not pay.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.detection import Evidence, detect
from resloc.cl.detection_landmark import landmark_links
from resloc.cl.detection_lockout import lockout_floor, record_lockout
from resloc.cl.detection_outvoted import widen_outvoted
from resloc.cl.detection_reciprocal import reciprocal_evidence
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_redundancy_fixes import capped_claims
from resloc.cl.detection_startup import claims_floored, floored_claims, startup_floor
from resloc.cl.detection_widening import keep_exempt
from resloc.cl.detection_witness import step_notes
from resloc.cl.detection_witness_frames import deliver_witness, record_witness
from resloc.cl.detection_zone import (
    materialize_with_reciprocal,
    reciprocal_position_fix,
    substitute_reciprocal,
)
from resloc.cl.detector import innovation_norm
from resloc.cl.fusion_methods import FusionStrategy, fusion_strategy
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.memory import LinkMemory
from resloc.cl.params import (
    CLParams,
    NeighbourEstimate,
    ThresholdInnovation,
    UpdateMode,
    at_robots,
)
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
    buffers: tuple[np.ndarray, np.ndarray] | None = None,
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
    buffers : (ndarray, ndarray), optional
        Float64 C-contiguous arrays of shapes (B, 3), (B, 3, 3) that receive the prediction
        and are returned (see :func:`check_buffers`), distinct from ``x`` and ``P``.
        Without them the prediction is in new arrays.

    Returns
    -------
    x, P : ndarray, shapes (B, 3), (B, 3, 3)

    Notes
    -----
    With the numba backend, the CKF, UKF and EKF predict in one compiled pass
    (:func:`resloc.cl.kernels_predict.fast_predict`, equal to this function to ~1e-15).
    """
    check_buffers(buffers, x, P)
    from resloc.cl.kernels_predict import fast_predict  # numba's import, on first use

    fast = fast_predict(filt, x, P, u, dt, params, buffers)
    if fast is not None:
        return fast
    Q = process_noise(x, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std))
    return _into(buffers, *filt.predict(x, P, u, dt, Q))


def check_buffers(buffers, x, P, links: LinkBatch | None = None) -> None:
    """Raise :class:`ValueError` unless ``buffers`` is None or a pair of writeable float64
    C-contiguous arrays shaped like ``x: (B, 3)`` and ``P: (B, 3, 3)`` sharing no memory
    with ``x``, ``P`` or (for a correction, ``links`` given) the neighbour estimates: the
    step reads those while it writes, and if it gives way to the reference path midway,
    the reference must see them unchanged."""
    if buffers is None:
        return
    try:
        bx, bP = buffers
    except (TypeError, ValueError):
        raise ValueError("buffers must be a pair (x, P) of arrays") from None
    for name, b, like in (("x", bx, x), ("P", bP, P)):
        if not (
            isinstance(b, np.ndarray)
            and b.dtype == np.float64
            and b.flags.c_contiguous
            and b.flags.writeable
            and b.shape == np.shape(like)
        ):
            raise ValueError(
                f"buffers: the {name} buffer must be a writeable C-contiguous float64 array "
                f"of shape {np.shape(like)}"
            )
    # the neighbour estimates where they are stored (reading links.x_nb would copy them)
    read = (x, P) if links is None else (x, P, *links.neighbour_rows()[1:])
    if any(np.may_share_memory(b, a) for b in (bx, bP) for a in read):
        raise ValueError(
            "buffers must not share memory with x, P or the neighbour estimates (keep two "
            "pairs of state arrays and alternate them)"
        )


def _into(buffers, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, P)``, written into ``buffers`` (returned) when given."""
    if buffers is None:
        return x, P
    buffers[0][...] = x
    buffers[1][...] = P
    return buffers[0], buffers[1]


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
    fusion: FusionStrategy,
    x_i: np.ndarray,
    P_i: np.ndarray,
    rows: np.ndarray,
    links: LinkBatch,
    params: CLParams,
    memory: LinkMemory | None,
    out: LinkOutcome,
    fixes: dict[str, np.ndarray] | None = None,
) -> tuple[np.ndarray, Moments, np.ndarray]:
    """Detector, trigger and channel for ``rows`` of ``links`` given robot estimates ``x_i``.

    Returns the rows to fuse, the moments to fuse them with (same order as ``rows``), the
    innovations and the observers' covariances to update (``P_i``, inflated where a
    detector stage re-admitted a measurement). Writes the per-link decisions into ``out``.
    ``fixes``: the step's position fixes of every link (the redundancy stage), or None.
    """
    ii, jj = links.i[rows], links.j[rows]
    R = params.R
    x_ref, P_ref = links.x_nb[rows], links.P_nb[rows]
    cached = params.neighbour_estimate is NeighbourEstimate.CACHED
    need_memory = cached or params.threshold_innovation is ThresholdInnovation.LAST_SENT
    if need_memory and memory is None:
        raise ValueError("cached neighbour estimates / last_sent threshold need a LinkMemory")
    known = np.ones(len(rows), dtype=bool)
    pos = np.zeros(len(rows), dtype=int)
    if need_memory:
        known, pos = memory.lookup(ii, jj)
    if cached:
        x_ref = np.where(known[:, None], memory.x[pos] if len(memory) else x_ref, x_ref)
        P_ref = np.where(known[:, None, None], memory.P[pos] if len(memory) else P_ref, P_ref)
    m = fusion.moments(filt, memory, x_i, P_i, x_ref, P_ref, ii, jj, R)
    z_rows = links.z[rows] if links.tamper is None else links.tamper(rows, m.z_hat, m.S)
    nu = innovation(z_rows, m.z_hat)
    substituted = None
    if params.zone_trust:
        # Zone-aware trust: a reading taken inside a mapped SDZ is replaced by the
        # partner's position fix when the partner, outside, measured the pair.
        z_partner = None if links.z_reciprocal is None else links.z_reciprocal[rows]
        substituted = substitute_reciprocal(x_i, links.x_nb[rows], z_partner, params)

    def position_fixes(m: Moments, sel: np.ndarray) -> Moments:
        # The substituted rows among ``sel`` get the partner's position fix (in place on nu).
        if substituted is None:
            return m
        s = sel[substituted[sel]]
        if not s.size:
            return m
        fix, nu[s] = reciprocal_position_fix(
            x_i[s], P_i[s], links.x_nb[rows[s]], links.P_nb[rows[s]], z_partner[s], R
        )
        return _with_rows(m, s, fix)

    m = position_fixes(m, np.arange(len(rows)))
    n_trig = innovation_norm(nu, m.S, params.trigger_norm, params.noise_std)
    if params.detector_norm == params.trigger_norm:
        n_det = n_trig
    else:
        n_det = innovation_norm(nu, m.S, params.detector_norm, params.noise_std)
    evidence = Evidence(
        nu,
        m.S,
        n_det,
        ii,
        jj,
        np.zeros(len(rows), bool),
        P_obs=P_i,
        x_obs=x_i,
        zone_substituted=substituted,
        **({} if fixes is None else {k: v[rows] for k, v in fixes.items()}),
    )
    detected = detect(evidence, params, memory)
    accepted = ~detected
    if evidence.inflation is not None:
        # A stage re-admitted these rows with the robot's covariance inflated (recovery
        # after a lock-out): the update uses the inflated covariance, so it can move the
        # estimate as far as the measurement says.
        r = np.flatnonzero(accepted & (evidence.inflation > 1.0))
        if r.size:
            P_i = P_i.copy()
            P_i[r] = P_i[r] * evidence.inflation[r, None, None]
            fresh = fusion.moments(
                filt, memory, x_i[r], P_i[r], x_ref[r], P_ref[r], ii[r], jj[r], R
            )
            m = _with_rows(m, r, fresh)
            nu[r] = innovation(z_rows[r], fresh.z_hat)
            m = position_fixes(m, r)
    if params.threshold_innovation is ThresholdInnovation.LAST_SENT:
        size = np.where(known, memory.last_norm[pos] if len(memory) else 0.0, 0.0)
    else:
        size = n_trig
    delta = event_threshold(
        at_robots(params.alpha, ii),
        links.lambda2[ii],
        at_robots(params.gamma, ii),
        size,
        at_robots(params.zeta_s, ii),
        links.risk_s[ii],
        at_robots(params.zeta_c, ii),
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
        rs = rows[sub]
        fresh = fusion.moments(
            filt, memory, x_i[sub], P_i[sub], links.x_nb[rs], links.P_nb[rs], ii[sub], jj[sub], R
        )
        m = _with_rows(m, sub, fresh)
        nu[sub] = innovation(z_rows[sub], fresh.z_hat)
        m = position_fixes(m, sub)
    return fuse, m, nu, P_i


def _with_rows(m: Moments, rows: np.ndarray, fresh: Moments) -> Moments:
    """A copy of ``m`` with ``rows`` replaced by ``fresh`` (same order)."""
    m = Moments(
        m.z_hat.copy(),
        m.S.copy(),
        m.Pxz.copy(),
        None if m.H_i is None else m.H_i.copy(),
        None if m.R_eff is None else m.R_eff.copy(),
    )
    m.z_hat[rows], m.S[rows], m.Pxz[rows] = fresh.z_hat, fresh.S, fresh.Pxz
    if m.H_i is not None:
        m.H_i[rows], m.R_eff[rows] = fresh.H_i, fresh.R_eff
    return m


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
    buffers: tuple[np.ndarray, np.ndarray] | None = None,
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
    buffers : (ndarray, ndarray), optional
        Arrays that receive the corrected estimates and are returned, as in
        :func:`predict`, distinct from ``x``, ``P`` and the neighbour estimates: at scale,
        a caller that keeps two pairs of state arrays, predicts from the first into the
        second and corrects back into the first, allocates no state per step. If an error
        is raised, their content is unspecified.

    Returns
    -------
    x, P : ndarray, shapes (B, 3), (B, 3, 3)
        Corrected estimates ``hat x_i,k|k``, ``P_i,k|k``.
    outcome : LinkOutcome
    """
    check_buffers(buffers, x, P, links)
    E = len(links)
    if E == 0:
        return (*_into(buffers, x, P), LinkOutcome.empty(E))
    from resloc.cl.kernels import fast_correct  # numba's import, on first use

    # A robot its observers' notes outvote widens its covariance first (both paths, and the
    # adversary's hook, see the widened one).
    P_before = P
    P = widen_outvoted(params, memory, links, P)
    P = startup_floor(params, memory, links, P)  # no robot shrinks below a floor at first
    if claims_floored(params, memory):  # nor trusts its neighbours' claims more at first
        claims = floored_claims(params, memory, links.i, links.P_nb)
        if claims is not links.P_nb:
            links = dataclasses.replace(links, P_nb=claims)
    P = lockout_floor(params, memory, links, P)  # nor stays locked out by its own gate
    if memory is not None:  # a compromised robot's software skips them (simulation)
        P = keep_exempt(P, P_before, memory.exempt)
    fast = fast_correct(filt, x, P, links, params, memory, buffers)
    if fast is None:
        x_new, P_new, out = _correct_reference(filt, x, P, links, params, memory)
        fast = (*_into(buffers, x_new, P_new), out)
    record_lockout(params, memory, links, fast[2], x)
    return fast


def _correct_reference(filt, x, P, links: LinkBatch, params: CLParams, memory):
    """The numpy correction of :func:`correct` (its executable specification)."""
    E = len(links)
    fusion = fusion_strategy(params.fusion)
    problem = fusion.problem(params)
    if problem is not None:
        raise ValueError(f"fusion {params.fusion.value!r} {problem}")
    claimed = links.P_nb if params.witness else None  # the claims as sent (witness notes)
    lie_notes = getattr(links.tamper, "notes", None)  # an adversary's own notes, if any
    if params.redundancy and params.redundancy_cap_fusion:
        # A neighbour weighs in the update no more than the redundancy test credited it.
        links = dataclasses.replace(links, P_nb=capped_claims(links.P_nb, links.i))
    links = landmark_links(params, links)  # a neighbour inside the map is a weak landmark
    if (
        ((params.zone_trust or params.reciprocal) and links.z_reciprocal is None)
        or (params.redundancy and links.tamper is not None)
        or (params.reciprocal and links.tamper is not None)
        or (params.witness and links.tamper is not None)
    ):
        # Every reading as reported (lies included) and its reverse link's range.
        pre = fusion.moments(
            filt, memory, x[links.i], P[links.i], links.x_nb, links.P_nb, links.i, links.j, params.R
        )
        # An adversary's hook may also say what the partners report (``reported``).
        reported = getattr(links.tamper, "reported", None)
        links = materialize_with_reciprocal(links, pre.z_hat, pre.S)
        if reported is not None:
            links = dataclasses.replace(links, z_reciprocal=reported(links.z_reciprocal))
    notes = None
    if params.witness:
        # The notes of the step before arrive with this step's frames (each receiver's
        # statistic); every reading's note on its neighbour waits for the next step's
        # frames (record_witness, at the end).
        deliver_witness(params, memory, links)
        notes = step_notes(
            links.z,
            x[links.i],
            P[links.i],
            links.x_nb,
            claimed,
            links.i,
            links.j,
            params,
            links.channel_ok,
        )
        if lie_notes is not None:
            notes = lie_notes(notes)
    fixes = None
    if params.redundancy:
        # Every link's fix of its observer, judged against the observer's other fixes of
        # the step at the predicted estimates (the same verdict in either update mode).
        fixes = fix_evidence(
            links.z,
            x[links.i],
            P[links.i],
            links.x_nb,
            links.P_nb,
            links.i,
            params,
            links.j,
            memory,
        )
    if params.reciprocal:
        # Every link's range against its partner's reading of the pair, once per step.
        fixes = {
            **(fixes or {}),
            **reciprocal_evidence(
                links.z,
                links.z_reciprocal,
                links.i,
                links.j,
                params,
                memory,
                x[links.i],
                links.x_nb,
            ),
        }
    out = LinkOutcome.empty(E)
    x = x.copy()
    P = P.copy()
    if params.update_mode is UpdateMode.SUMMED:
        rows = np.arange(E)
        xi, Pi = x[links.i], P[links.i]
        fuse, m, nu, P_used = _decide(filt, fusion, xi, Pi, rows, links, params, memory, out, fixes)
        f = np.flatnonzero(fuse)
        if f.size:
            ii = links.i[f]
            Pi = P[ii]
            x_upd, P_upd = kalman_update(x[ii], P_used[f], nu[f], _take(m, f))
            np.add.at(x, ii, x_upd - x[ii])
            np.add.at(P, ii, P_upd - Pi)
            x[:, 2] = wrap_angle(x[:, 2])
            # One repair per robot, not per link (ii repeats a robot with several links).
            touched, first = np.unique(ii, return_index=True)
            Pt = P[touched]
            P[touched], bad = _ensure_pd(0.5 * (Pt + np.swapaxes(Pt, -1, -2)))
            out.repaired[f[first[bad]]] = True
        record_witness(notes, params, memory)
        return x, P, out

    # Sequential: round r fuses every robot's r-th link (robots are independent in a step).
    start = np.searchsorted(links.i, links.i, side="left")
    rank = np.arange(E) - start
    order = np.argsort(rank, kind="stable")
    bounds = np.searchsorted(rank[order], np.arange(int(rank.max()) + 2))
    for r in range(len(bounds) - 1):
        rows = order[bounds[r] : bounds[r + 1]]
        ii = links.i[rows]  # distinct within a round
        fuse, m, nu, P_used = _decide(
            filt, fusion, x[ii], P[ii], rows, links, params, memory, out, fixes
        )
        if not fuse.any():
            continue
        f = np.flatnonzero(fuse)
        rf, obs = rows[f], ii[f]
        x_new, P_new = fusion.update(
            memory,
            x[obs],
            P_used[f],
            obs,
            links.j[rf],
            links.x_nb[rf],
            links.P_nb[rf],
            None if links.P_nb_ind is None else links.P_nb_ind[rf],
            nu[f],
            _take(m, f),
            params,
        )
        P_new, bad = _ensure_pd(P_new)
        out.repaired[rf[bad]] = True
        x[obs] = x_new
        P[obs] = P_new
    P = fusion.finish(memory, P, links.j, out.delivered)
    record_witness(notes, params, memory)
    return x, P, out
