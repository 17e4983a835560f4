"""Compiled fast path of the CL correction (:func:`resloc.cl.step.correct`).

One call processes every link of a :class:`~resloc.cl.step.LinkBatch` (all robots of all
trials) in one compiled loop: for each link, in row order (robot ``i``'s links in ascending
``j``), the joint sigma-point moments (CKF/UKF, 12/13 points over ``[x_i; x_j]``) or the
linearized moments (EKF), the innovation (eq. 9), the detector and trigger norms, the attack
detector, the adaptive threshold (eq. 11), the event condition (eq. 10), the channel (eq. 8),
the Kalman gain by a 2 x 2 Cholesky solve, the Schur (CKF/UKF) or Joseph (EKF) covariance
update, the symmetrization, the positive-definiteness check and, where it fails, the
eigenvalue repair. Robots are independent within a step (a link reads only robot ``i``'s
running estimate and ``j``'s transmitted estimate), so the row-order loop gives exactly the
rounds of the reference path.

The kernels need `numba <https://numba.pydata.org>`_ (the optional extra ``fast``). Without
it, or for options the kernel does not cover, :func:`~resloc.cl.step.correct` runs its
numpy reference path; both agree to round-off (tested to 1e-9).

Covered: ``update_mode = sequential``, ``neighbour_estimate = current``, every detector and
trigger norm, ``threshold_innovation`` ``current`` and ``last_sent``, scalar or per-robot
gains, the exact :class:`~resloc.filters.SigmaPointFilter` (any rule on 6-D points,
circular or arithmetic means) and :class:`~resloc.filters.ExtendedFilter` types.
Not covered (reference path): ``summed`` updates, ``cached`` neighbour estimates, duplicated
``(i, j)`` rows, any other filter class, and any :class:`~resloc.cl.params.CLParams` or
:class:`~resloc.cl.step.LinkBatch` field added later unless it holds its default value.

The backend is chosen by :func:`set_backend` / :func:`use_backend`, or by the environment
variable ``RESLOC_BACKEND`` (``auto``, ``numba`` or ``numpy``) read at import.
"""

from __future__ import annotations

import dataclasses
import math
import os
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from resloc.cl.detector import InnovationNorm
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.errors import ConfigError
from resloc.filters.ekf import ExtendedFilter
from resloc.filters.sigma_points import SigmaPointFilter
from resloc.linalg import JITTER_LEVELS
from resloc.models.measurement import MIN_RANGE

try:  # numba is optional: `pip install resloc[fast]`
    import numba

    HAVE_NUMBA = True
    _jit = numba.njit(cache=True, nogil=True)
except ImportError:  # pragma: no cover - exercised only where numba is absent
    HAVE_NUMBA = False

    def _jit(func):
        return func


__all__ = [
    "HAVE_NUMBA",
    "FastCorrection",
    "backend",
    "fast_correct",
    "set_backend",
    "use_backend",
    "warm_up",
]

_BACKENDS = ("auto", "numba", "numpy")
_backend = "auto"

#: Norm codes shared with the kernel.
_NORM_CODE = {InnovationNorm.EUCLIDEAN: 0, InnovationNorm.SCALED: 1, InnovationNorm.NIS: 2}
_JITTER = np.asarray(JITTER_LEVELS, dtype=float)

#: Kernel status codes.
OK = 0
NOT_PD = 1  # a Cholesky factorization failed even with the largest jitter, or NaN/inf


def set_backend(name: str) -> None:
    """Choose the CL correction backend.

    Parameters
    ----------
    name : {"auto", "numba", "numpy"}
        ``auto``: the compiled kernels when numba is importable, else numpy.
        ``numba``: the kernels (error if numba is missing). ``numpy``: always the reference.
    """
    global _backend
    if name not in _BACKENDS:
        raise ConfigError(f"backend must be one of {list(_BACKENDS)}, got {name!r}")
    if name == "numba" and not HAVE_NUMBA:
        raise ConfigError("backend 'numba' needs numba: pip install 'resloc[fast]'")
    _backend = name


def backend() -> str:
    """The backend in effect: ``numba`` or ``numpy``."""
    return "numba" if _backend != "numpy" and HAVE_NUMBA else "numpy"


@contextmanager
def use_backend(name: str) -> Iterator[None]:
    """Context manager: run the enclosed code with backend ``name``, then restore."""
    previous = _backend
    set_backend(name)
    try:
        yield
    finally:
        set_backend(previous)


_env = os.environ.get("RESLOC_BACKEND", "auto").strip().lower() or "auto"
if _env in _BACKENDS and not (_env == "numba" and not HAVE_NUMBA):
    _backend = _env


@dataclass
class FastCorrection:
    """Result of :func:`fast_correct`: corrected estimates and per-link decisions.

    Shapes: ``x (B, 3)``, ``P (B, 3, 3)``; every other array ``(E,)``.
    """

    x: np.ndarray
    P: np.ndarray
    norm: np.ndarray
    threshold: np.ndarray
    detected: np.ndarray
    triggered: np.ndarray
    delivered: np.ndarray
    fused: np.ndarray
    repaired: np.ndarray


_filter_specs: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _filter_spec(filt) -> tuple | None:
    """:func:`_build_filter_spec`, cached per filter object (filters are immutable)."""
    try:
        return _filter_specs[filt]
    except KeyError:
        spec = _build_filter_spec(filt)
        _filter_specs[filt] = spec
        return spec
    except TypeError:  # not hashable or not weakly referenceable
        return _build_filter_spec(filt)


def _build_filter_spec(filt) -> tuple | None:
    """``(mode, nz_idx, nz_val, nz_cnt, Wm, Wc, circular)`` for a filter the kernel
    reproduces, else None. The 6-D unit points are passed by their non-zero entries
    (ascending column), which gives the same sums as the dense product."""
    if type(filt) is ExtendedFilter:
        w = np.zeros(1)
        return 1, np.zeros((1, 6), np.int64), np.zeros((1, 6)), np.zeros(1, np.int64), w, w, True
    if type(filt) is SigmaPointFilter and filt.rule6.unit.shape[1] == 6:
        r = filt.rule6
        unit = np.asarray(r.unit, dtype=float)
        m = unit.shape[0]
        nz_idx = np.zeros((m, 6), np.int64)
        nz_val = np.zeros((m, 6))
        nz_cnt = np.zeros(m, np.int64)
        for k in range(m):
            cols = np.flatnonzero(unit[k])
            nz_cnt[k] = len(cols)
            nz_idx[k, : len(cols)] = cols
            nz_val[k, : len(cols)] = unit[k, cols]
        return (
            0,
            nz_idx,
            nz_val,
            nz_cnt,
            np.ascontiguousarray(r.Wm, dtype=float),
            np.ascontiguousarray(r.Wc, dtype=float),
            bool(filt.circular),
        )
    return None


#: CLParams fields the kernel implements. Any other field must hold its default value for
#: the fast path to run (options added later fall back to the reference path by default).
_COVERED = frozenset(
    {
        "range_std",
        "bearing_std",
        "odometry_std",
        "process_floor_std",
        "detector",
        "rho",
        "detector_norm",
        "trigger",
        "alpha",
        "gamma",
        "zeta_s",
        "zeta_c",
        "trigger_norm",
        "risk_factor_floor",
        "threshold_innovation",
        "update_mode",
        "neighbour_estimate",
        "update_without_transmission",  # only acts with cached estimates (not covered)
        "extra",
    }
)


#: LinkBatch fields the kernel reads; any other field (a hook added later) must hold its
#: default value for the fast path to run.
_LINK_FIELDS = frozenset(
    {"i", "j", "z", "x_nb", "P_nb", "channel_ok", "risk_s", "risk_c", "lambda2"}
)


def _only_covered_options(obj, covered: frozenset = _COVERED) -> bool:
    """True if every dataclass field of ``obj`` outside ``covered`` holds its default."""
    for f in dataclasses.fields(obj):
        if f.name in covered:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            return False
        value = getattr(obj, f.name)
        if value is default:
            continue
        try:
            same = np.shape(value) == np.shape(default) and bool(np.all(value == default))
        except (TypeError, ValueError):
            same = False
        if not same:
            return False
    return True


_params_cache: tuple = (None, None)


def _prepare_params(params: CLParams) -> tuple | None:
    """The kernel's parameter arguments, or None if the options are not covered. Cached for
    the last ``params`` object (a frozen dataclass)."""
    global _params_cache
    ref, prepared = _params_cache
    if ref is not None and ref() is params:
        return prepared
    prepared = None
    if (
        _only_covered_options(params)
        and params.update_mode is UpdateMode.SEQUENTIAL
        and params.neighbour_estimate is NeighbourEstimate.CURRENT
    ):
        prepared = (
            _per_robot(params.rho),
            _per_robot(params.alpha),
            _per_robot(params.gamma),
            _per_robot(params.zeta_s),
            _per_robot(params.zeta_c),
            np.ascontiguousarray(params.R, dtype=float),
            np.ascontiguousarray(params.noise_std, dtype=float),
            bool(params.detector),
            bool(params.trigger),
            _NORM_CODE[params.detector_norm],
            _NORM_CODE[params.trigger_norm],
            float(params.risk_factor_floor),
        )
    try:
        _params_cache = (weakref.ref(params), prepared)
    except TypeError:  # not weakly referenceable: no cache
        _params_cache = (None, None)
    return prepared


def _shapes_ok(x, P, links, li, prepared) -> bool:
    """Every index the kernel will use is in range (the compiled loop does not check)."""
    E = len(li)
    if E == 0:
        return False
    B = int(li.max()) + 1
    if li.min() < 0 or np.shape(x)[0] < B or np.shape(P)[0] < B:
        return False
    if np.shape(x)[1:] != (3,) or np.shape(P)[1:] != (3, 3):
        return False
    per_link = (
        (links.z, (E, 2)),
        (links.x_nb, (E, 3)),
        (links.P_nb, (E, 3, 3)),
        (links.channel_ok, (E,)),
        (links.j, (E,)),
    )
    if any(np.shape(a) != shape for a, shape in per_link):
        return False
    if any(np.ndim(a) != 1 or len(a) < B for a in (links.risk_s, links.risk_c, links.lambda2)):
        return False
    return all(a.shape[0] == 1 or a.shape[0] >= B for a in prepared[:5])


def _per_robot(v) -> np.ndarray:
    """A scalar or per-robot gain as a contiguous float array of shape (1,) or (B,)."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(v, dtype=float)).ravel())


def fast_correct(filt, x, P, links, params: CLParams, memory=None) -> FastCorrection | None:
    """The whole correction of :func:`~resloc.cl.step.correct` in one compiled call.

    Returns ``None`` when the kernel does not cover the filter or the options, when the
    backend is ``numpy``, or when a covariance is not positive definite (the caller then
    runs the reference path, which raises the library's :class:`NumericalError`). Nothing
    is modified in that case. Otherwise ``memory`` (needed only for ``last_sent``) is
    updated with the delivered links, as the reference does.

    Shapes as in :func:`~resloc.cl.step.correct`.
    """
    if backend() != "numba":
        return None
    prepared = _prepare_params(params)
    spec = _filter_spec(filt)
    if prepared is None or spec is None:
        return None
    if dataclasses.is_dataclass(links) and not _only_covered_options(links, _LINK_FIELDS):
        return None
    last_sent = params.threshold_innovation is ThresholdInnovation.LAST_SENT
    if last_sent and memory is None:
        return None  # the reference path raises the explanatory error
    li = np.ascontiguousarray(links.i, dtype=np.int64)
    lj = np.asarray(links.j, dtype=np.int64)
    E = len(li)
    if not _shapes_ok(x, P, links, li, prepared):
        return None  # the reference path raises on inconsistent input (no bounds checks here)
    if E > 1 and np.any((li[1:] == li[:-1]) & (lj[1:] == lj[:-1])):
        return None  # a duplicated link would read its own store within one call
    last = np.zeros(E if last_sent else 0)
    if last_sent and len(memory):
        known, pos = memory.lookup(li, lj)
        last = np.where(known, memory.last_norm[pos], 0.0)
    mode, nz_idx, nz_val, nz_cnt, Wm, Wc, circular = spec
    x_out = np.array(x, dtype=float, order="C", copy=True)
    P_out = np.array(P, dtype=float, order="C", copy=True)
    norm = np.empty(E)
    threshold = np.empty(E)
    flags = np.zeros((5, E), dtype=np.bool_)  # detected, triggered, delivered, fused, repaired
    status = _correct_links(
        x_out,
        P_out,
        li,
        np.ascontiguousarray(links.z, dtype=float),
        np.ascontiguousarray(links.x_nb, dtype=float),
        np.ascontiguousarray(links.P_nb, dtype=float),
        np.ascontiguousarray(links.channel_ok, dtype=np.bool_),
        np.ascontiguousarray(links.risk_s, dtype=float),
        np.ascontiguousarray(links.risk_c, dtype=float),
        np.ascontiguousarray(links.lambda2, dtype=float),
        *prepared[:7],
        nz_idx,
        nz_val,
        nz_cnt,
        Wm,
        Wc,
        mode,
        circular,
        *prepared[7:],
        last_sent,
        last,
        _JITTER,
        norm,
        threshold,
        flags,
    )
    if status != OK:
        return None
    detected, triggered, delivered, fused, repaired = flags
    if last_sent and delivered.any():
        d = np.flatnonzero(delivered)
        memory.store(links.i[d], links.j[d], links.x_nb[d], links.P_nb[d], norm[d])
    return FastCorrection(
        x_out, P_out, norm, threshold, detected, triggered, delivered, fused, repaired
    )


def warm_up() -> bool:
    """Compile (or load from the on-disk cache) the kernels outside any timed section.

    Returns
    -------
    bool
        Whether the compiled kernels are in use.
    """
    if backend() != "numba":
        return False
    from resloc.cl.step import LinkBatch
    from resloc.filters.base import make_filter

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
_MIN_R2 = MIN_RANGE**2


@_jit
def _wrap(a):
    """``np.mod(a + pi, 2 pi) - pi`` (numpy's floored modulo, bit for bit)."""
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
    """Solve ``L L^T x = b`` (the order of :func:`resloc.linalg.solve_spd`)."""
    y0 = b0 / l00
    y1 = (b1 - l10 * y0) / l11
    x1 = y1 / l11
    x0 = (y0 - l10 * x1) / l00
    return x0, x1


@_jit
def _norm(kind, nu0, nu1, std0, std1, l00, l10, l11):
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


@_jit
def _correct_links(
    x, P, li, z, x_nb, P_nb, channel_ok, risk_s, risk_c, lambda2,
    rho, alpha, gamma, zeta_s, zeta_c, R, noise_std, nz_idx, nz_val, nz_cnt, Wm, Wc,
    mode, circular, detector, trigger, det_norm, trig_norm, risk_floor,
    last_sent, last, jitter, out_norm, out_threshold, flags,
):  # fmt: skip
    """Every link of one step in row order; updates ``x, P`` in place.

    Returns the status; on a non-OK status the outputs are partial and must be
    discarded.
    """
    E = li.shape[0]
    m = Wm.shape[0]
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
    std0 = noise_std[0]
    std1 = noise_std[1]
    same_norm = det_norm == trig_norm
    for e in range(E):
        i = li[e]
        Pi = P[i]
        Pj = P_nb[e]
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        xj0 = x_nb[e, 0]
        xj1 = x_nb[e, 1]
        re00 = 0.0
        re01 = 0.0
        re11 = 0.0
        if mode == 0:
            # ---- joint sigma points over [x_i; x_j], P = blockdiag(P_i, P_j)
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
                Z1[k] = _wrap(math.atan2(dy, dx) - th)
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
            zh1 = _wrap(math.atan2(ssin, scos)) if circular else _wrap(zb)
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
        else:
            # ---- EKF: first-order moments of eq. (3)
            dx = xj0 - xi0
            dy = xj1 - xi1
            q = dx * dx + dy * dy
            if q < _MIN_R2:
                q = _MIN_R2
            r = math.sqrt(q)
            Hj[0, 0] = dx / r
            Hj[0, 1] = dy / r
            Hj[0, 2] = 0.0
            Hj[1, 0] = -dy / q
            Hj[1, 1] = dx / q
            Hj[1, 2] = 0.0
            for a in range(2):
                for b in range(3):
                    Hi[a, b] = -Hj[a, b]
            Hi[1, 2] = -1.0
            zh0 = math.hypot(dx, dy)
            zh1 = _wrap(math.atan2(dy, dx) - xi2)
            # R_eff = Hj Pj Hj^T + R ; S = Hi Pi Hi^T + R_eff (then both symmetrized)
            for a in range(2):
                for b in range(3):
                    s = 0.0
                    for c in range(3):
                        s += Hj[a, c] * Pj[c, b]
                    T3[a, b] = s
            rj00 = 0.0
            rj01 = 0.0
            rj10 = 0.0
            rj11 = 0.0
            for c in range(3):
                rj00 += T3[0, c] * Hj[0, c]
                rj01 += T3[0, c] * Hj[1, c]
                rj10 += T3[1, c] * Hj[0, c]
                rj11 += T3[1, c] * Hj[1, c]
            rj00 += R[0, 0]
            rj01 += R[0, 1]
            rj10 += R[1, 0]
            rj11 += R[1, 1]
            for a in range(2):
                for b in range(3):
                    s = 0.0
                    for c in range(3):
                        s += Hi[a, c] * Pi[c, b]
                    T3[a, b] = s
            si00 = 0.0
            si01 = 0.0
            si10 = 0.0
            si11 = 0.0
            for c in range(3):
                si00 += T3[0, c] * Hi[0, c]
                si01 += T3[0, c] * Hi[1, c]
                si10 += T3[1, c] * Hi[0, c]
                si11 += T3[1, c] * Hi[1, c]
            S00 = si00 + rj00
            S01 = 0.5 * ((si01 + rj01) + (si10 + rj10))
            S11 = si11 + rj11
            re00 = rj00
            re01 = 0.5 * (rj01 + rj10)
            re11 = rj11
            for a in range(3):
                for b in range(2):
                    s = 0.0
                    for c in range(3):
                        s += Pi[a, c] * Hi[b, c]
                    Pxz[a, b] = s
        # ---- innovation (eq. 9), norms, detector, threshold (eq. 11), trigger (eq. 10)
        nu0 = z[e, 0] - zh0
        nu1 = _wrap(z[e, 1] - zh1)
        l00, l10, l11 = _chol2(S00, S01, S11, jitter)
        if l00 == 0.0:
            return NOT_PD
        n_trig = _norm(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
        n_det = n_trig if same_norm else _norm(det_norm, nu0, nu1, std0, std1, l00, l10, l11)
        rho_i = rho[i] if rho.shape[0] > 1 else rho[0]
        detected = detector and n_det > rho_i
        size = last[e] if last_sent else n_trig
        a_i = alpha[i] if alpha.shape[0] > 1 else alpha[0]
        g_i = gamma[i] if gamma.shape[0] > 1 else gamma[0]
        zs_i = zeta_s[i] if zeta_s.shape[0] > 1 else zeta_s[0]
        zc_i = zeta_c[i] if zeta_c.shape[0] > 1 else zeta_c[0]
        risk = 1.0 - zs_i * risk_s[i] - zc_i * risk_c[i]
        if risk < risk_floor:
            risk = risk_floor
        l2 = lambda2[i]
        scale = a_i / l2 if l2 > 0.0 else math.inf
        delta = scale * (1.0 + g_i * size) * risk
        if math.isnan(delta):
            delta = math.inf
        fire = (n_trig > delta) if trigger else True
        triggered = (not detected) and fire
        delivered = triggered and channel_ok[e]
        out_norm[e] = n_trig
        out_threshold[e] = math.nan if detected else delta
        flags[0, e] = detected
        flags[1, e] = triggered
        flags[2, e] = delivered
        flags[3, e] = delivered
        if not delivered:
            continue
        # ---- Kalman update of x_i: K = Pxz S^-1 by the Cholesky solve
        for a in range(3):
            k0, k1 = _solve2(l00, l10, l11, Pxz[a, 0], Pxz[a, 1])
            K[a, 0] = k0
            K[a, 1] = k1
        x[i, 0] = xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)
        x[i, 1] = xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)
        x[i, 2] = _wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1))
        if mode == 0:
            # P - K S K^T (Schur complement)
            for a in range(3):
                t0 = K[a, 0] * S00 + K[a, 1] * S01
                t1 = K[a, 0] * S01 + K[a, 1] * S11
                for b in range(3):
                    Pn[a, b] = Pi[a, b] - (t0 * K[b, 0] + t1 * K[b, 1])
        else:
            # Joseph form (I - K H) P (I - K H)^T + K R_eff K^T
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
        for a in range(3):
            for b in range(3):
                T3[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
        if not _is_pd3(T3):
            _repair3(T3)
            flags[4, e] = True
        for a in range(3):
            for b in range(3):
                P[i, a, b] = T3[a, b]
    return OK
