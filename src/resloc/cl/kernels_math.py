"""Scalar math primitives of the compiled CL kernels (numba, the optional extra ``fast``).

Each is the compiled twin of a numpy function of the library, named in its docstring
(``docs/algorithm.md`` maps them): the angle wrap, the 3 x 3 and 2 x 2 Cholesky factors with
escalating jitter, the 2 x 2 solve, the Sylvester positive-definiteness check, the
eigenvalue repair and the ``H P H^T`` sandwich. The link loop (:mod:`resloc.cl.kernels_links`)
calls them; the jit decorators the kernel modules share are defined here.
"""

from __future__ import annotations

import functools
import hashlib
import math
import sys
import types
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

from resloc.cl.backend import HAVE_NUMBA


def callee_modules(dispatcher) -> set:
    """The modules of every compiled function ``dispatcher`` calls or inlines, directly or
    through its callees (by the global names its code reads: a function, or a module and
    its attributes), its own module excluded unless reached through another one."""
    seen: set = set()
    modules: set = set()
    pending = [dispatcher]
    while pending:
        current = pending.pop()
        if id(current) in seen:
            continue
        seen.add(id(current))
        func = current.py_func
        names: set = set()
        codes = [func.__code__]
        while codes:  # the function's code and the code objects nested in it
            code = codes.pop()
            names.update(code.co_names)
            codes.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
        scope = func.__globals__
        for name in names:
            value = scope.get(name)
            found = [value]
            if isinstance(value, types.ModuleType):  # ``module.function``
                found = [getattr(value, attr, None) for attr in names]
            for callee in found:
                if _is_dispatcher(callee) and id(callee) not in seen:
                    modules.add(sys.modules[callee.py_func.__module__])
                    pending.append(callee)
    return modules


def _is_dispatcher(value) -> bool:
    return HAVE_NUMBA and isinstance(value, numba.core.registry.CPUDispatcher)


def stamp_with_pieces(dispatcher, *modules) -> None:
    """Make ``dispatcher``'s on-disk cache stale when ``modules`` change, beside the modules
    of its callees that every kernel of :data:`jit`, :data:`jit_inline` and
    :data:`jit_lanes` is stamped with (for a module it reads data from, or a kernel made
    by another decorator)."""
    cache_file = _stamp_lazily(dispatcher)
    if cache_file is not None:
        cache_file._resloc_extra = (*cache_file._resloc_extra, *modules)
        cache_file._resloc_stamp = None


def _stamp_lazily(dispatcher):
    """Stamp ``dispatcher``'s on-disk cache with the sources of the modules of every
    compiled function it calls or inlines (:func:`callee_modules`), computed on the first
    cache access (all modules are imported by then). numba stamps a cached kernel with its
    own source file only, and a caller's cache holds its callees' code: an edited
    :mod:`resloc.cl.kernels_ci_weight` would otherwise leave :mod:`resloc.cl.kernels_split`'s
    cached kernel running the old code. Returns the cache file (None: numba absent, or a
    numba whose cache we do not know)."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    if getattr(cache_file, "_source_stamp", None) is None:
        return None
    cls = type(cache_file)
    if not issubclass(cls, _LazyStamp):
        cache_file.__class__ = _lazy_stamp_class(cls)
        cache_file._resloc_dispatcher = dispatcher
        cache_file._resloc_extra = ()
        cache_file._resloc_stamp = None
    return cache_file


class _LazyStamp:
    """Mixin of a numba cache file whose ``_source_stamp`` is numba's (the source file's)
    plus a digest of the sources of the kernel's callee modules."""

    @property
    def _source_stamp(self):
        own = self.__dict__["_source_stamp"]
        stamp = self.__dict__.get("_resloc_stamp")
        if stamp is None:
            dispatcher = self.__dict__["_resloc_dispatcher"]
            home = sys.modules[dispatcher.py_func.__module__]
            pieces = ({*self._resloc_extra} | callee_modules(dispatcher)) - {home}
            digest = hashlib.sha256()
            for path in sorted(str(module.__file__) for module in pieces):
                digest.update(Path(path).read_bytes())
            dispatcher._resloc_pieces = frozenset(module.__name__ for module in pieces)
            stamp = (own, digest.hexdigest())
            self.__dict__["_resloc_stamp"] = stamp
        return stamp

    @_source_stamp.setter
    def _source_stamp(self, value):
        self.__dict__["_source_stamp"] = value


_LAZY_CLASSES: dict = {}


def _lazy_stamp_class(cls):
    if cls not in _LAZY_CLASSES:
        _LAZY_CLASSES[cls] = type(cls.__name__, (_LazyStamp, cls), {})
    return _LAZY_CLASSES[cls]


if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    def _stamped(decorator):
        """``decorator`` (a cached ``numba.njit``) whose kernels' cache stamps cover the
        modules of their callees (:func:`stamp_with_pieces`)."""

        def apply(func):
            dispatcher = decorator(func)
            _stamp_lazily(dispatcher)
            return dispatcher

        return apply

    jit = _stamped(numba.njit(cache=True, nogil=True))
    # The per-link pieces are inlined into the loop: a call that passes arrays (the named
    # structures hold ~20) costs a reference-count update per array, per link.
    jit_inline = _stamped(numba.njit(cache=True, nogil=True, inline="always"))
    # The SIMD stages (lanes, rounds, points): error_model="numpy" makes a float division
    # IEEE (no ZeroDivisionError branch), which lets LLVM vectorize their loops.
    jit_lanes = _stamped(numba.njit(cache=True, nogil=True, error_model="numpy"))
else:  # pragma: no cover - exercised only where numba is absent

    def jit(func):
        return func

    jit_inline = jit
    jit_lanes = jit


_PI = math.pi
_TWO_PI = 2.0 * math.pi


@jit
def wrap(a):
    """``np.mod(a + pi, 2 pi) - pi`` (numpy's floored modulo, bit for bit).
    Twin: :func:`resloc.angles.wrap_angle`."""
    t = a + _PI
    if 0.0 <= t < _TWO_PI:
        return t - _PI  # fmod(t, 2 pi) == t exactly here: the common case, no division
    return t % _TWO_PI - _PI  # Python's float modulo is numpy's npy_divmod


@jit
def chol3(A, L, jitter):
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


@jit
def chol2(s00, s10, s11, jitter):
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


@jit
def solve2(l00, l10, l11, b0, b1):
    """Solve ``L L^T x = b`` (the order of :func:`resloc.linalg.solve_spd`, its twin)."""
    y0 = b0 / l00
    y1 = (b1 - l10 * y0) / l11
    x1 = y1 / l11
    x0 = (y0 - l10 * x1) / l00
    return x0, x1


@jit
def is_pd3(P):
    """Sylvester's criterion, as :func:`resloc.filters.covariance_is_pd`."""
    a = P[0, 0]
    m2 = P[0, 0] * P[1, 1] - P[0, 1] * P[1, 0]
    det = (
        P[0, 0] * (P[1, 1] * P[2, 2] - P[1, 2] * P[2, 1])
        - P[0, 1] * (P[1, 0] * P[2, 2] - P[1, 2] * P[2, 0])
        + P[0, 2] * (P[1, 0] * P[2, 1] - P[1, 1] * P[2, 0])
    )
    return a > 0.0 and m2 > 0.0 and det > 0.0 and math.isfinite(det)


@jit
def repair3(P):
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


@jit_inline
def lower_bound(a, key, lo, hi):
    """The first position in the sorted ``a[lo:hi]`` whose value is not below ``key``
    (``lo + np.searchsorted(a[lo:hi], key)``, side left); ``hi`` when there is none.
    Inlined into its callers (a call per link costs more than the search)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@jit_inline
def store_covariance(P, i, Pn, T3):
    """``P[i]`` = the symmetric part of the updated covariance ``Pn``, repaired when it is
    not positive definite (``T3``: 3 x 3 scratch); returns whether it was repaired. Twin:
    :func:`resloc.linalg.symmetrize` then :func:`resloc.filters.repair_covariance`."""
    for a in range(3):
        for b in range(3):
            T3[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
    repaired = not is_pd3(T3)
    if repaired:
        repair3(T3)
    for a in range(3):
        for b in range(3):
            P[i, a, b] = T3[a, b]
    return repaired


@jit_inline
def mul3(X, Y, out):
    """``out = X Y`` of 3 x 3 matrices."""
    for a in range(3):
        for b in range(3):
            out[a, b] = X[a, 0] * Y[0, b] + X[a, 1] * Y[1, b] + X[a, 2] * Y[2, b]


@jit_inline
def mul3_t(X, Y, out):
    """``out = X Y^T`` of 3 x 3 matrices."""
    for a in range(3):
        for b in range(3):
            out[a, b] = X[a, 0] * Y[b, 0] + X[a, 1] * Y[b, 1] + X[a, 2] * Y[b, 2]


@jit_inline
def entries3(M):
    """The nine entries of a 3 x 3 matrix by row, as a tuple (kept in registers)."""
    return (
        M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2],
    )  # fmt: skip


@jit_inline
def sandwich(H, P, T):
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


def per_params(func: Callable) -> Callable:
    """Keep ``func(params)`` for the last ``params`` object: a run passes the same frozen
    :class:`~resloc.cl.params.CLParams` every step, and the kernels' inputs derived from it
    (contiguous gain arrays, codes) would otherwise be rebuilt per step."""
    last: list = [None, None]

    @functools.wraps(func)
    def cached(params):
        ref, value = last
        if ref is not None and ref() is params:
            return value
        value = func(params)
        try:
            last[:] = [weakref.ref(params), value]
        except TypeError:  # not weakly referenceable: no cache
            last[:] = [None, None]
        return value

    return cached


def gain_array(v) -> np.ndarray:
    """A scalar or per-robot option (gain, threshold, ...) as the contiguous float64
    vector the kernels take (shape (1,) or (N,))."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(v, dtype=float)).ravel())
