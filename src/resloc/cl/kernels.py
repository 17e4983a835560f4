"""Compiled twin of the CL correction (:func:`resloc.cl.step.correct`).

One call processes every link of a :class:`~resloc.cl.links.LinkBatch` (all robots of all
trials) in one compiled loop over the links in row order (robot ``i``'s links in ascending
``j``). Robots are independent within a step (a link reads only robot ``i``'s running
estimate and ``j``'s transmitted estimate), so the row-order loop gives exactly the rounds of
the reference path. Each piece of a link's work is a named function beside the numpy
function it twins (``docs/algorithm.md`` maps every equation to both):

============================  ======================  =============================================
kernel function               paper                   numpy twin
============================  ======================  =============================================
``_correct_links`` (block)    eq. (3), Algorithm 1    ``SigmaPointFilter.relative_moments``
:func:`_linearized_moments`   eq. (3), linearized     ``ExtendedFilter.relative_moments``
:func:`_innovation_norm`      eq. (9), detector       :func:`resloc.cl.detector.innovation_norm`
:func:`_event_threshold`      eq. (11)                :func:`resloc.cl.trigger.event_threshold`
:func:`_gate_link`            Algorithm 1, detector   :func:`resloc.cl.detector.attack_detected`
``detect_link`` (CUSUMs)     beyond the paper        :func:`resloc.cl.detection.detect`
:func:`_decide_link`          Alg. 1, eqs. (8), (10)  ``resloc.cl.step._decide``
``_correct_links`` (block)    Algorithm 1, gain       :func:`resloc.filters.update.kalman_gain`
:func:`_schur_update`         Algorithm 1             :func:`resloc.filters.update.kalman_update`
``_correct_links`` (block)    Algorithm 1 (EKF)       :func:`resloc.filters.update.kalman_update`
============================  ======================  =============================================

What the kernel covers is decided by :func:`resloc.cl.backend.kernel_refusal` from the
strategies; the inputs are named structures (:class:`KernelLinks`, :class:`KernelRobots`,
:class:`KernelOptions`, :class:`~resloc.cl.backend.FilterKernelSpec`,
:class:`~resloc.cl.kernels_detection.KernelDetection`, :class:`KernelOutputs`). The detector
stages that keep per-link state (the CUSUMs) are in :mod:`resloc.cl.kernels_detection`.
"""

from __future__ import annotations

import hashlib
import math
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_tamper as _kernels_tamper
from resloc.cl import kernels_trig as _kernels_trig
from resloc.cl.backend import (  # backend choice re-exported for callers of this module
    HAVE_NUMBA,
    FilterKernelSpec,
    backend,
    filter_kernel_spec,
    kernel_refusal,
    set_backend,
    use_backend,
)
from resloc.cl.fusion import FusionMethod
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_detection import NORM_CODE, detect_link, detector_state
from resloc.cl.kernels_gauge import (
    gauge_commit,
    gauge_record,
    gauge_state,
    no_gauge,
    range_bearing_jacobians_into,
)
from resloc.cl.kernels_tamper import no_tamper, stealthy_measurement
from resloc.cl.kernels_trig import fast_atan2
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.params import CLParams, ThresholdInnovation
from resloc.linalg import JITTER_LEVELS

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    # The per-link pieces are inlined into the loop: a call that passes arrays (the named
    # structures hold ~20) costs a reference-count update per array, per link.
    _jit_inline = numba.njit(cache=True, nogil=True, inline="always")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit(func):
        return func

    _jit_inline = _jit


__all__ = [
    "HAVE_NUMBA",
    "KernelLinks",
    "KernelOptions",
    "KernelOutputs",
    "KernelRobots",
    "backend",
    "fast_correct",
    "set_backend",
    "use_backend",
    "warm_up",
]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)

#: Kernel status codes.
OK = 0
NOT_PD = 1  # a Cholesky factorization failed even with the largest jitter, or NaN/inf


class KernelLinks(NamedTuple):
    """Per-link inputs, each with leading axis E (rows sorted by observer)."""

    i: np.ndarray  # (E,) int64 observers
    z: np.ndarray  # (E, 2) measured range, bearing
    x_nb: np.ndarray  # (S, 3) transmitted estimates: link e's is row nb[e]
    P_nb: np.ndarray  # (S, 3, 3)
    nb: np.ndarray  # (E,) int64 row of x_nb / P_nb (LinkBatch.neighbour_rows)
    channel_ok: np.ndarray  # (E,) bool
    last_norm: np.ndarray  # (E,) last delivered norm (``last_sent``), else (0,)


class KernelRobots(NamedTuple):
    """Per-robot inputs ``(B,)``; the gains are ``(1,)`` (scalar) or ``(B,)``."""

    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    rho: np.ndarray
    alpha: np.ndarray
    gamma: np.ndarray
    zeta_s: np.ndarray
    zeta_c: np.ndarray


class KernelOptions(NamedTuple):
    """The step's scalar options and constants."""

    R: np.ndarray  # (2, 2)
    noise_std: np.ndarray  # (2,)
    detector: bool
    trigger: bool
    detector_norm: int  # NORM_CODE
    trigger_norm: int
    risk_factor_floor: float
    last_sent: bool
    jitter: np.ndarray  # escalating Cholesky jitter levels


class KernelOutputs(NamedTuple):
    """Per-link decisions, written by the kernel."""

    norm: np.ndarray  # (E,)
    threshold: np.ndarray  # (E,)
    flags: np.ndarray  # (5, E) bool: detected, triggered, delivered, fused, repaired


class CompiledBookkeeping(NamedTuple):
    """What a fusion method with a compiled twin records beside the kernel's update.

    Attributes
    ----------
    state : callable ``(memory, E) -> KernelGauge or None``
        (:class:`~resloc.cl.kernels_gauge.KernelGauge`)
        The kernel's working arrays for ``E`` links (None: the kernel cannot run it).
    commit : callable ``(memory, state, i, j, fused) -> None``
        Hands the kernel's records to the method's state in ``memory``.
    """

    state: Callable
    commit: Callable


def _nothing_to_commit(memory, state, i, j, fused) -> None:
    del memory, state, i, j, fused


def _gauge_commit(memory, state, i, j, fused) -> None:
    gauge_commit(memory.joint, state, i, j, fused)


#: Per fusion method with ``compiled = True``: its bookkeeping in the compiled path.
COMPILED_BOOKKEEPING: dict[FusionMethod, CompiledBookkeeping] = {
    FusionMethod.NAIVE: CompiledBookkeeping(lambda memory, E: no_gauge(E), _nothing_to_commit),
    FusionMethod.GAUGE: CompiledBookkeeping(
        lambda memory, E: None if memory is None else gauge_state(memory.joint, E),
        _gauge_commit,
    ),
}


def _per_robot(v) -> np.ndarray:
    """A scalar or per-robot gain as a contiguous float array of shape (1,) or (B,)."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(v, dtype=float)).ravel())


def _contiguous(a, dtype=float) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


_last_prepared: tuple = (None, None)


def _prepared(params: CLParams) -> tuple[tuple[np.ndarray, ...], KernelOptions]:
    """The gains ``(rho, alpha, gamma, zeta_s, zeta_c)`` and the options of ``params`` as
    the kernel takes them, kept for the last ``params`` object (frozen)."""
    global _last_prepared
    ref, prepared = _last_prepared
    if ref is not None and ref() is params:
        return prepared
    gains = params.rho, params.alpha, params.gamma, params.zeta_s, params.zeta_c
    options = KernelOptions(
        _contiguous(params.R),
        _contiguous(params.noise_std),
        bool(params.detector),
        bool(params.trigger),
        NORM_CODE[params.detector_norm],
        NORM_CODE[params.trigger_norm],
        float(params.risk_factor_floor),
        params.threshold_innovation is ThresholdInnovation.LAST_SENT,
        _JITTER,
    )
    prepared = (tuple(_per_robot(g) for g in gains), options)
    try:
        _last_prepared = (weakref.ref(params), prepared)
    except TypeError:  # not weakly referenceable: no cache
        _last_prepared = (None, None)
    return prepared


def _shapes_ok(x, P, links: LinkBatch, robots: KernelRobots, neighbours) -> bool:
    """Every index the kernel will use is in range (the compiled loop does not check)."""
    li = np.asarray(links.i)
    E = len(li)
    B = int(li.max()) + 1
    if li.min() < 0 or np.shape(x)[0] < B or np.shape(P)[0] < B:
        return False
    if np.shape(x)[1:] != (3,) or np.shape(P)[1:] != (3, 3):
        return False
    nb, x_nb, P_nb = neighbours
    S = len(x_nb)
    if np.shape(x_nb) != (S, 3) or np.shape(P_nb) != (S, 3, 3):
        return False
    if nb is not None and (np.shape(nb) != (E,) or nb.min() < 0 or nb.max() >= S):
        return False
    per_link = (
        (links.z, (E, 2)),
        (x_nb, (E, 3) if nb is None else (S, 3)),
        (links.channel_ok, (E,)),
        (links.j, (E,)),
    )
    if any(np.shape(a) != shape for a, shape in per_link):
        return False
    if any(a.ndim != 1 or len(a) < B for a in robots[:3]):
        return False
    return all(a.shape[0] == 1 or a.shape[0] >= B for a in robots[3:])


def fast_correct(
    filt, x, P, links: LinkBatch, params: CLParams, memory=None
) -> tuple[np.ndarray, np.ndarray, LinkOutcome] | None:
    """The whole correction of :func:`~resloc.cl.step.correct` in one compiled call.

    Returns ``None`` when :func:`~resloc.cl.backend.kernel_refusal` gives a reason, when the
    input is inconsistent (the reference path then raises the explanatory error) or when a
    covariance is not positive definite (the reference path raises the library's
    :class:`NumericalError`). Nothing is modified in that case. Otherwise ``memory`` (read
    only with ``last_sent``) is updated with the delivered links, as the reference does.

    Shapes as in :func:`~resloc.cl.step.correct`; the outcome has ``compiled = True``.
    """
    if kernel_refusal(filt, params, links, memory) is not None:
        return None
    last_sent = params.threshold_innovation is ThresholdInnovation.LAST_SENT
    if last_sent and memory is None:
        return None  # the reference path raises the explanatory error
    li = _contiguous(links.i, np.int64)
    lj = np.asarray(links.j, dtype=np.int64)
    E = len(li)
    gains, options = _prepared(params)
    robots = KernelRobots(
        _contiguous(links.risk_s), _contiguous(links.risk_c), _contiguous(links.lambda2), *gains
    )
    neighbours = links.neighbour_rows()
    if E == 0 or not _shapes_ok(x, P, links, robots, neighbours):
        return None
    if E > 1 and np.any((li[1:] == li[:-1]) & (lj[1:] == lj[:-1])):
        return None  # a duplicated link would read its own store within one call
    strategy = fusion_strategy(params.fusion)
    if strategy.problem(params) is not None:
        return None  # the reference path raises the explanatory error
    bookkeeping = COMPILED_BOOKKEEPING[strategy.method]
    gauge = bookkeeping.state(memory, E)
    if gauge is None:
        return None  # the reference path raises the explanatory error, or records exactly
    detection = detector_state(params, memory, li, lj)
    if detection is None:
        return None  # the reference path raises the explanatory error
    last = np.zeros(E if last_sent else 0)
    if last_sent and len(memory):
        known, pos = memory.lookup(li, lj)
        last = np.where(known, memory.last_norm[pos], 0.0)
    tamper = no_tamper() if links.tamper is None else links.tamper.kernel_form
    z = links.z
    if tamper.on:  # the attacker's honest measurements and observers must be this batch's
        if tamper.z.shape != (E, 2) or not np.array_equal(tamper.observer, li):
            return None
        z = tamper.z
    nb, x_nb, P_nb = neighbours
    kernel_links = KernelLinks(
        li,
        _contiguous(z),
        _contiguous(x_nb),
        _contiguous(P_nb),
        np.arange(E, dtype=np.int64) if nb is None else _contiguous(nb, np.int64),
        _contiguous(links.channel_ok, np.bool_),
        last,
    )
    out = KernelOutputs(np.empty(E), np.empty(E), np.zeros((5, E), dtype=np.bool_))
    x_out = np.array(x, dtype=float, order="C", copy=True)
    P_out = np.array(P, dtype=float, order="C", copy=True)
    spec: FilterKernelSpec = filter_kernel_spec(filt)
    detect = detection.kernel
    status = _correct_links(
        x_out, P_out, kernel_links, robots, spec, options, detect, gauge, tamper, out
    )
    if status != OK:
        detection.undo()
        return None
    detected, triggered, delivered, fused, repaired = out.flags
    bookkeeping.commit(memory, gauge, li, lj, fused)
    P_out = strategy.finish(memory, P_out, lj, delivered)
    if last_sent and delivered.any():
        d = np.flatnonzero(delivered)
        rows = d if nb is None else nb[d]
        memory.store(links.i[d], links.j[d], x_nb[rows], P_nb[rows], out.norm[d])
    outcome = LinkOutcome(
        out.norm, out.threshold, detected, triggered, delivered, fused, repaired, compiled=True
    )
    return x_out, P_out, outcome


def warm_up() -> bool:
    """Compile (or load from the on-disk cache) the kernels outside any timed section.

    Returns
    -------
    bool
        Whether the compiled kernels are in use.
    """
    from resloc.filters.base import make_filter

    if backend() != "numba":
        return False
    x = np.array([[0.0, 0.0, 0.1], [1.0, 0.5, -0.2]])
    P = np.broadcast_to(0.01 * np.eye(3), (2, 3, 3)).copy()
    links = LinkBatch(
        np.array([0, 1]), np.array([1, 0]), np.array([[1.1, 0.4], [1.1, 2.9]]),
        x[[1, 0]], P[[1, 0]], np.array([True, True]), np.zeros(2), np.zeros(2), np.ones(2),
    )  # fmt: skip
    for kind in ("ckf", "ekf"):
        fast_correct(make_filter(kind), x, P, links, CLParams())
    return True


# ---------------------------------------------------------------------------------------
# The kernels. Written in plain Python over scalars and tiny arrays; compiled by numba.
# ---------------------------------------------------------------------------------------
_PI = math.pi
_TWO_PI = 2.0 * math.pi


@_jit
def _wrap(a):
    """``np.mod(a + pi, 2 pi) - pi`` (numpy's floored modulo, bit for bit).
    Twin: :func:`resloc.angles.wrap_angle`."""
    t = a + _PI
    if 0.0 <= t < _TWO_PI:
        return t - _PI  # fmod(t, 2 pi) == t exactly here: the common case, no division
    return t % _TWO_PI - _PI  # Python's float modulo is numpy's npy_divmod


@_jit
def _chol3(A, L, jitter):
    """Lower Cholesky factor of a 3 x 3 ``A`` into ``L``, escalating jitter as
    :func:`resloc.linalg.cholesky_jitter` does. Returns False if none succeeds."""
    for r in range(3):
        for c in range(3):
            if not math.isfinite(A[r, c]):
                return False
    scale = (abs(A[0, 0]) + abs(A[1, 1]) + abs(A[2, 2])) / 3.0
    if scale < 1e-300:
        scale = 1e-300
    for level in jitter:
        eps = level * scale
        ok = True
        for c in range(3):
            s = A[c, c] + eps
            for k in range(c):
                s -= L[c, k] * L[c, k]
            if not s > 0.0:
                ok = False
                break
            d = math.sqrt(s)
            L[c, c] = d
            for r in range(c + 1, 3):
                t = A[r, c]
                for k in range(c):
                    t -= L[r, k] * L[c, k]
                L[r, c] = t / d
            for r in range(c):
                L[r, c] = 0.0
        if ok:
            return True
    return False


@_jit
def _chol2(s00, s10, s11, jitter):
    """Lower Cholesky factor ``(l00, l10, l11)`` of a 2 x 2 SPD matrix, with jitter.
    ``l00 = 0`` signals failure."""
    if not (math.isfinite(s00) and math.isfinite(s10) and math.isfinite(s11)):
        return 0.0, 0.0, 0.0
    scale = (abs(s00) + abs(s11)) / 2.0
    if scale < 1e-300:
        scale = 1e-300
    for level in jitter:
        eps = level * scale
        a = s00 + eps
        if not a > 0.0:
            continue
        l00 = math.sqrt(a)
        l10 = s10 / l00
        b = s11 + eps - l10 * l10
        if not b > 0.0:
            continue
        return l00, l10, math.sqrt(b)
    return 0.0, 0.0, 0.0


@_jit
def _solve2(l00, l10, l11, b0, b1):
    """Solve ``L L^T x = b`` (the order of :func:`resloc.linalg.solve_spd`, its twin)."""
    y0 = b0 / l00
    y1 = (b1 - l10 * y0) / l11
    x1 = y1 / l11
    x0 = (y0 - l10 * x1) / l00
    return x0, x1


@_jit_inline
def _innovation_norm(kind, nu0, nu1, std0, std1, l00, l10, l11):
    """Size of the innovation ``Lambda_ij`` of eq. (9) in the norm ``kind`` (a
    :data:`NORM_CODE`). Twin: :func:`resloc.cl.detector.innovation_norm`."""
    if kind == 0:
        return math.hypot(nu0, nu1)
    if kind == 1:
        return math.hypot(nu0 / std0, nu1 / std1)
    w0, w1 = _solve2(l00, l10, l11, nu0, nu1)
    q = nu0 * w0 + nu1 * w1
    return math.sqrt(q if q > 0.0 else 0.0)


@_jit
def _is_pd3(P):
    """Sylvester's criterion, as :func:`resloc.filters.covariance_is_pd`."""
    a = P[0, 0]
    m2 = P[0, 0] * P[1, 1] - P[0, 1] * P[1, 0]
    det = (
        P[0, 0] * (P[1, 1] * P[2, 2] - P[1, 2] * P[2, 1])
        - P[0, 1] * (P[1, 0] * P[2, 2] - P[1, 2] * P[2, 0])
        + P[0, 2] * (P[1, 0] * P[2, 1] - P[1, 1] * P[2, 0])
    )
    return a > 0.0 and m2 > 0.0 and det > 0.0 and math.isfinite(det)


@_jit
def _repair3(P):
    """Eigenvalue clipping in place, as :func:`resloc.filters.repair_covariance`."""
    S = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            S[r, c] = 0.5 * (P[r, c] + P[c, r])
    w, V = np.linalg.eigh(S)
    tr = abs(P[0, 0] + P[1, 1] + P[2, 2])
    floor = 1e-12 * (tr if tr > 1e-300 else 1e-300)
    for k in range(3):
        if w[k] < floor:
            w[k] = floor
    A = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            s = 0.0
            for k in range(3):
                s += V[r, k] * w[k] * V[c, k]
            A[r, c] = s
    for r in range(3):
        for c in range(3):
            P[r, c] = 0.5 * (A[r, c] + A[c, r])


@_jit_inline
def _sandwich(H, P, T):
    """``H P H^T`` of a 2 x 3 ``H`` and a 3 x 3 ``P`` as ``(q00, q01, q10, q11)`` (``T``:
    2 x 3 scratch)."""
    for a in range(2):
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += H[a, c] * P[c, b]
            T[a, b] = s
    q00 = 0.0
    q01 = 0.0
    q10 = 0.0
    q11 = 0.0
    for c in range(3):
        q00 += T[0, c] * H[0, c]
        q01 += T[0, c] * H[1, c]
        q10 += T[1, c] * H[0, c]
        q11 += T[1, c] * H[1, c]
    return q00, q01, q10, q11


@_jit_inline
def _linearized_moments(xi0, xi1, xi2, Pi, xj0, xj1, Pj, R, Hi, Hj, T3, Pxz):
    """First-order moments of eq. (3) with the range/bearing Jacobians at the means; fills
    ``work.Pxz`` and ``work.Hi``.

    Twin: :meth:`resloc.filters.ekf.ExtendedFilter.relative_moments`.
    Returns ``(zh0, zh1, S00, S01, S11, re00, re01, re11)`` with ``R_eff = H_j P_j H_j^T + R``
    (``T3``: scratch).
    """
    dx = xj0 - xi0
    dy = xj1 - xi1
    range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
    zh0 = math.hypot(dx, dy)
    zh1 = _wrap(math.atan2(dy, dx) - xi2)
    # R_eff = Hj Pj Hj^T + R ; S = Hi Pi Hi^T + R_eff (then both symmetrized)
    rj00, rj01, rj10, rj11 = _sandwich(Hj, Pj, T3)
    rj00 += R[0, 0]
    rj01 += R[0, 1]
    rj10 += R[1, 0]
    rj11 += R[1, 1]
    si00, si01, si10, si11 = _sandwich(Hi, Pi, T3)
    S00 = si00 + rj00
    S01 = 0.5 * ((si01 + rj01) + (si10 + rj10))
    S11 = si11 + rj11
    for a in range(3):
        for b in range(2):
            s = 0.0
            for c in range(3):
                s += Pi[a, c] * Hi[b, c]
            Pxz[a, b] = s
    return zh0, zh1, S00, S01, S11, rj00, 0.5 * (rj01 + rj10), rj11


@_jit_inline
def _event_threshold(alpha, lambda2, gamma, size, zeta_s, risk_s, zeta_c, risk_c, floor):
    """Adaptive threshold ``delta_ij`` of eq. (11) of one link (the observer's gains, risks
    and ``lambda2``; ``size``: the innovation size in the threshold).
    Twin: :func:`resloc.cl.trigger.event_threshold`."""
    risk = 1.0 - zeta_s * risk_s - zeta_c * risk_c
    if risk < floor:
        risk = floor
    scale = alpha / lambda2 if lambda2 > 0.0 else math.inf
    delta = scale * (1.0 + gamma * size) * risk
    if math.isnan(delta):
        delta = math.inf
    return delta


@_jit_inline
def _gate_link(n_det, detector, rho):
    """Attack detection of Algorithm 1: discard when the detector norm exceeds ``rho``.
    Twin: :func:`resloc.cl.detector.attack_detected` (the ``gate`` stage)."""
    return detector and n_det > rho


@_jit_inline
def _decide_link(detected, n_trig, delta, trigger, channel_ok):
    """Event condition (eq. 10) and channel (eq. 8) of one link the detector judged:
    ``(triggered, delivered)``. Twin: ``resloc.cl.step._decide``."""
    fire = (n_trig > delta) if trigger else True
    triggered = (not detected) and fire
    return triggered, triggered and channel_ok


@_jit_inline
def _schur_update(Pi, K, S00, S01, S11, Pn):
    """``P - K S K^T`` into ``Pn`` (sigma-point filters).
    Twin: :func:`resloc.filters.update.kalman_update`."""
    for a in range(3):
        t0 = K[a, 0] * S00 + K[a, 1] * S01
        t1 = K[a, 0] * S01 + K[a, 1] * S11
        for b in range(3):
            Pn[a, b] = Pi[a, b] - (t0 * K[b, 0] + t1 * K[b, 1])


@_jit
def _correct_links(x, P, links, robots, filt, options, detection, gauge, tamper, out):
    """Every link of one step in row order; updates ``x: (B, 3)``, ``P: (B, 3, 3)`` in place.

    The structures are unpacked once, here: a field read inside the loop would cost a
    reference-count update per field and link. For the same reason the pieces that would
    take many arrays (the sigma-point moments, the gain, the Joseph update) are blocks of
    this loop, each citing its twin; measured, as functions they cost 15-20% of the
    correction. Returns the status; on a non-OK status the outputs are partial and must be
    discarded.
    """
    li, z, x_nb, P_nb, nb, channel_ok, last_norm = links
    risk_s, risk_c, lambda2, rho, alpha, gamma, zeta_s, zeta_c = robots
    linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt
    R, noise_std, detector, trigger, det_norm, trig_norm, risk_floor, last_sent, jitter = options
    out_norm, out_threshold, flags = out
    m = Wm.shape[0]
    Pi = np.zeros((3, 3))
    Pj = np.zeros((3, 3))
    Li = np.zeros((3, 3))
    Lj = np.zeros((3, 3))
    off = np.zeros((m, 6))
    Z0 = np.zeros(m)
    Z1 = np.zeros(m)
    Pxz = np.zeros((3, 2))
    K = np.zeros((3, 2))
    Hi = np.zeros((2, 3))
    Hj = np.zeros((2, 3))
    Pn = np.zeros((3, 3))
    T3 = np.zeros((3, 3))
    A3 = np.zeros((3, 3))
    G3 = np.zeros((3, 3))
    std0 = noise_std[0]
    std1 = noise_std[1]
    record_gauge = gauge[0]
    tampered = tamper[0]
    attacked = tamper[3]
    fused = flags[3]
    first = 0  # robot i's first row
    for e in range(li.shape[0]):
        i = li[e]
        if e > 0 and li[e - 1] != i:
            first = e
        n = nb[e]  # j's transmitted estimate, read by index: no per-link copy
        # P_i and P_j into scratch matrices: a view (P[i]) costs atomic reference-count
        # updates per link (measured: the EKF's link 20% faster, the CKF's ~3%).
        for a in range(3):
            for b in range(3):
                Pi[a, b] = P[i, a, b]
                Pj[a, b] = P_nb[n, a, b]
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        xj0 = x_nb[n, 0]
        xj1 = x_nb[n, 1]
        re00 = 0.0
        re01 = 0.0
        re11 = 0.0
        if linearized:
            zh0, zh1, S00, S01, S11, re00, re01, re11 = _linearized_moments(
                xi0, xi1, xi2, Pi, xj0, xj1, Pj, R, Hi, Hj, T3, Pxz
            )
        else:
            # Moments of z_ij (eq. 3) from the filter's sigma points over [x_i; x_j] with
            # P = blockdiag(P_i, P_j) (twin: SigmaPointFilter.relative_moments).
            if not _chol3(Pi, Li, jitter) or not _chol3(Pj, Lj, jitter):
                return NOT_PD
            for k in range(m):
                for a in range(6):
                    off[k, a] = 0.0
                for t in range(nz_cnt[k]):
                    b = nz_idx[k, t]
                    u = nz_val[k, t]
                    if b < 3:
                        for a in range(3):
                            off[k, a] += Li[a, b] * u
                    else:
                        for a in range(3):
                            off[k, 3 + a] += Lj[a, b - 3] * u
            zr = 0.0
            ssin = 0.0
            scos = 0.0
            zb = 0.0
            sin_i = 0.0
            cos_i = 0.0
            if circular:
                sin_i = math.sin(xi2)
                cos_i = math.cos(xi2)
            for k in range(m):
                dx = (xj0 + off[k, 3]) - (xi0 + off[k, 0])
                dy = (xj1 + off[k, 4]) - (xi1 + off[k, 1])
                r = math.sqrt(dx * dx + dy * dy)
                th = xi2 + off[k, 2]
                Z0[k] = r
                Z1[k] = _wrap(fast_atan2(dy, dx) - th)
                zr += r * Wm[k]
                if circular:
                    # sin and cos of the bearing atan2(dy, dx) - th, without sin/cos of it
                    if r > 0.0:
                        if off[k, 2] == 0.0:
                            sn = sin_i
                            cs = cos_i
                        else:
                            sn = math.sin(th)
                            cs = math.cos(th)
                        ssin += ((dy * cs - dx * sn) / r) * Wm[k]
                        scos += ((dx * cs + dy * sn) / r) * Wm[k]
                    else:
                        ssin += math.sin(Z1[k]) * Wm[k]
                        scos += math.cos(Z1[k]) * Wm[k]
                else:
                    zb += Z1[k] * Wm[k]
            zh0 = zr
            zh1 = _wrap(fast_atan2(ssin, scos)) if circular else _wrap(zb)
            mx0 = 0.0
            mx1 = 0.0
            mx2 = 0.0
            for k in range(m):
                mx0 += off[k, 0] * Wm[k]
                mx1 += off[k, 1] * Wm[k]
                mx2 += off[k, 2] * Wm[k]
            s00 = 0.0
            s01 = 0.0
            s11 = 0.0
            for a in range(3):
                Pxz[a, 0] = 0.0
                Pxz[a, 1] = 0.0
            for k in range(m):
                d0 = Z0[k] - zh0
                d1 = _wrap(Z1[k] - zh1)
                w = Wc[k]
                s00 += d0 * w * d0
                s01 += d0 * w * d1
                s11 += d1 * w * d1
                g0 = off[k, 0] - mx0
                g1 = off[k, 1] - mx1
                g2 = off[k, 2] - mx2
                Pxz[0, 0] += g0 * w * d0
                Pxz[0, 1] += g0 * w * d1
                Pxz[1, 0] += g1 * w * d0
                Pxz[1, 1] += g1 * w * d1
                Pxz[2, 0] += g2 * w * d0
                Pxz[2, 1] += g2 * w * d1
            S00 = s00 + R[0, 0]
            S01 = 0.5 * ((s01 + R[0, 1]) + (s01 + R[1, 0]))
            S11 = s11 + R[1, 1]
        # innovation, eq. (9)
        nu0 = z[e, 0] - zh0
        nu1 = _wrap(z[e, 1] - zh1)
        l00, l10, l11 = _chol2(S00, S01, S11, jitter)
        if l00 == 0.0:
            return NOT_PD
        if tampered and attacked[e]:  # the stealthy attacker sees z_hat and S (twin: tamper)
            zt0, zt1 = stealthy_measurement(tamper, i, z[e, 0], z[e, 1], nu0, nu1, l00, l10, l11)
            nu0 = zt0 - zh0
            nu1 = _wrap(_wrap(zt1) - zh1)
        n_trig = _innovation_norm(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
        if det_norm == trig_norm:
            n_det = n_trig
        else:
            n_det = _innovation_norm(det_norm, nu0, nu1, std0, std1, l00, l10, l11)
        a_i = alpha[i] if alpha.shape[0] > 1 else alpha[0]
        g_i = gamma[i] if gamma.shape[0] > 1 else gamma[0]
        zs_i = zeta_s[i] if zeta_s.shape[0] > 1 else zeta_s[0]
        zc_i = zeta_c[i] if zeta_c.shape[0] > 1 else zeta_c[0]
        rho_i = rho[i] if rho.shape[0] > 1 else rho[0]
        delta = _event_threshold(
            a_i, lambda2[i], g_i, last_norm[e] if last_sent else n_trig,
            zs_i, risk_s[i], zc_i, risk_c[i], risk_floor,
        )  # fmt: skip
        gated = _gate_link(n_det, detector, rho_i)
        detected = detect_link(detection, e, i, gated, nu0, nu1, n_det, det_norm, l00, l10, l11)
        triggered, delivered = _decide_link(detected, n_trig, delta, trigger, channel_ok[e])
        out_norm[e] = n_trig
        out_threshold[e] = math.nan if detected else delta
        flags[0, e] = detected
        flags[1, e] = triggered
        flags[2, e] = delivered
        flags[3, e] = delivered
        if not delivered:
            continue
        # Kalman gain K = P^xz S^-1 by the Cholesky factor of S (twin: kalman_gain)
        for a in range(3):
            k0, k1 = _solve2(l00, l10, l11, Pxz[a, 0], Pxz[a, 1])
            K[a, 0] = k0
            K[a, 1] = k1
        x[i, 0] = xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)
        x[i, 1] = xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)
        x[i, 2] = _wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1))
        if linearized:
            # Joseph form (I - K H) P (I - K H)^T + K R_eff K^T (EKF; twin: kalman_update)
            for a in range(3):
                for b in range(3):
                    A3[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * Hi[0, b] + K[a, 1] * Hi[1, b])
            for a in range(3):
                for b in range(3):
                    s = 0.0
                    for c in range(3):
                        s += A3[a, c] * Pi[c, b]
                    T3[a, b] = s
            for a in range(3):
                t0 = K[a, 0] * re00 + K[a, 1] * re01
                t1 = K[a, 0] * re01 + K[a, 1] * re11
                for b in range(3):
                    s = 0.0
                    for c in range(3):
                        s += T3[a, c] * A3[b, c]
                    Pn[a, b] = s + (t0 * K[b, 0] + t1 * K[b, 1])
        else:
            _schur_update(Pi, K, S00, S01, S11, Pn)
        for a in range(3):
            for b in range(3):
                T3[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
        if not _is_pd3(T3):
            _repair3(T3)
            flags[4, e] = True
        for a in range(3):
            for b in range(3):
                P[i, a, b] = T3[a, b]
        if record_gauge:
            gauge_record(gauge, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G3, T3)
    return OK


def _stamp_with_pieces(dispatcher, *modules) -> None:
    """Make ``dispatcher``'s on-disk cache stale when a module whose pieces it inlines
    changes: numba stamps a cached kernel with its own source file only, so an edited
    :mod:`resloc.cl.kernels_detection` would otherwise keep running the old compiled code."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    if getattr(cache_file, "_source_stamp", None) is None:
        return  # numba absent, or a numba whose cache we do not know: nothing to extend
    digest = hashlib.sha256()
    for module in modules:
        digest.update(Path(module.__file__).read_bytes())
    cache_file._source_stamp = (cache_file._source_stamp, digest.hexdigest())


_stamp_with_pieces(
    _correct_links, _kernels_detection, _kernels_gauge, _kernels_tamper, _kernels_trig
)

#: Public names of the scalar primitives the compiled prediction
#: (:mod:`resloc.cl.kernels_predict`) builds on.
wrap_scalar = _wrap
cholesky3 = _chol3
