"""Which path runs the CL correction: the numpy reference or its compiled twin.

:func:`resloc.cl.step.correct` is the executable specification. Its compiled twin
(:mod:`resloc.cl.kernels`, needs `numba <https://numba.pydata.org>`_, the optional extra
``fast``) runs a correction when the backend allows it and :func:`kernel_refusal` finds
nothing it does not implement. Coverage is read from the strategies, not listed here: a
fusion method's :attr:`~resloc.cl.fusion_methods.FusionStrategy.compiled`, every active
detector stage's :attr:`~resloc.cl.detection.DetectorStage.compiled`, the filter's compiled
description (:func:`filter_kernel_spec`), and :data:`COMPILED_CHOICES` for the two choices
that are not strategies.

The backend is chosen by :func:`set_backend` / :func:`use_backend`, or by the environment
variable ``RESLOC_BACKEND`` (``auto``, ``numba`` or ``numpy``) read at import.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NamedTuple

import numpy as np

from resloc.cl.detection import active_stages
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams, NeighbourEstimate, UpdateMode
from resloc.errors import ConfigError
from resloc.filters.ekf import ExtendedFilter
from resloc.filters.sigma_points import SigmaPointFilter

#: Whether numba (the optional extra ``fast``) is installed.
HAVE_NUMBA = importlib.util.find_spec("numba") is not None

__all__ = [
    "COMPILED_CHOICES",
    "HAVE_NUMBA",
    "FilterKernelSpec",
    "backend",
    "c_float",
    "filter_kernel_spec",
    "kernel_refusal",
    "per_filter",
    "set_backend",
    "use_backend",
]

_BACKENDS = ("auto", "numba", "numpy")
_backend = "auto"

#: The compiled twin implements these values of the choices that are not strategies.
COMPILED_CHOICES = {
    "update_mode": frozenset({UpdateMode.SEQUENTIAL, UpdateMode.SUMMED}),
    "neighbour_estimate": frozenset({NeighbourEstimate.CURRENT, NeighbourEstimate.CACHED}),
}


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


def c_float(a) -> np.ndarray:
    """``a`` itself when it is a C-contiguous float64 array (the run's), else a copy that
    is: what the compiled kernels take, without a copy in the common case."""
    if type(a) is np.ndarray and a.dtype == _FLOAT and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(a, dtype=float)


_FLOAT = np.dtype(float)


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


class FilterKernelSpec(NamedTuple):
    """A filter as the kernel sees it.

    Attributes
    ----------
    linearized : bool
        EKF moments (True) or sigma points (False).
    nz_idx : ndarray of int, shape (m, 6)
        Column of each non-zero entry of the 6-D unit points (ascending).
    nz_val : ndarray, shape (m, 6)
        Those entries (the sums equal the dense product's).
    nz_cnt : ndarray of int, shape (m,)
        Non-zero entries per point.
    Wm, Wc : ndarray, shape (m,)
        Mean and covariance weights.
    circular : bool
        Circular mean of the bearings.
    """

    linearized: bool
    nz_idx: np.ndarray
    nz_val: np.ndarray
    nz_cnt: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray
    circular: bool


def per_filter(build: Callable) -> Callable:
    """``build(filt)`` kept per filter object (filters are immutable); a filter that is not
    hashable or weakly referenceable is described anew each call."""
    specs: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    @functools.wraps(build)
    def cached(filt):
        try:
            return specs[filt]
        except KeyError:
            spec = specs[filt] = build(filt)
            return spec
        except TypeError:
            return build(filt)

    return cached


def _build_filter_spec(filt) -> FilterKernelSpec | None:
    if type(filt) is ExtendedFilter:
        w = np.zeros(1)
        return FilterKernelSpec(
            True, np.zeros((1, 6), np.int64), np.zeros((1, 6)), np.zeros(1, np.int64), w, w, True
        )
    if type(filt) is not SigmaPointFilter or filt.rule6.unit.shape[1] != 6:
        return None
    unit = np.asarray(filt.rule6.unit, dtype=float)
    m = unit.shape[0]
    nz_idx = np.zeros((m, 6), np.int64)
    nz_val = np.zeros((m, 6))
    nz_cnt = np.zeros(m, np.int64)
    for k in range(m):
        cols = np.flatnonzero(unit[k])
        nz_cnt[k] = len(cols)
        nz_idx[k, : len(cols)] = cols
        nz_val[k, : len(cols)] = unit[k, cols]
    return FilterKernelSpec(
        False,
        nz_idx,
        nz_val,
        nz_cnt,
        np.ascontiguousarray(filt.rule6.Wm, dtype=float),
        np.ascontiguousarray(filt.rule6.Wc, dtype=float),
        bool(filt.circular),
    )


#: The kernel's description of a filter, or None when the kernel does not reproduce it.
filter_kernel_spec = per_filter(_build_filter_spec)


def kernel_refusal(filt, params: CLParams, links: LinkBatch, memory=None) -> str | None:
    """Why the compiled kernel does not run this correction; None when it does.

    Parameters
    ----------
    filt : GaussianFilter
    params : CLParams
    links : LinkBatch
    memory : LinkMemory, optional

    Returns
    -------
    str or None
    """
    if backend() != "numba":
        return "the backend is numpy"
    if filter_kernel_spec(filt) is None:
        return f"the filter {type(filt).__name__} has no compiled twin"
    refusal = _params_refusal(params)
    if refusal is not None:
        return refusal
    # (with the redundancy stage, the reciprocal check or the witness on, or zone trust
    # without the partners' readings, the hook is applied to every row before the kernel,
    # as the reference does: resloc.cl.kernels_redundancy.capped_links,
    # resloc.cl.kernels_reciprocal.partner_readings, resloc.cl.kernels_zone.zone_links)
    materialized = (
        params.redundancy
        or params.reciprocal
        or params.witness
        or (params.zone_trust and links.z_reciprocal is None)
    )
    hook = links.tamper is not None and not materialized
    if hook and getattr(links.tamper, "kernel_form", None) is None:
        return "an adversary's tamper hook without a compiled form (kernel_form) runs in Python"
    split = fusion_strategy(params.fusion).kernel_update == "split_ci"
    if links.P_nb_ind is not None and not split:
        return "transmitted independent parts belong to split covariance intersection"
    if split and links.P_nb_ind is None:
        return "split CI needs the transmitted independent parts (LinkBatch.P_nb_ind)"
    return None


_last_params: tuple = (None, None)


def _summed_refusal(params: CLParams) -> str | None:
    """The combinations the compiled summed update (:mod:`resloc.cl.kernels_summed`) lacks:
    it fuses with the Kalman update alone."""
    if params.update_mode is not UpdateMode.SUMMED:
        return None
    strategy = fusion_strategy(params.fusion)
    if strategy.kernel_update != "kalman" or strategy.kernel_bookkeeping != "none":
        return f"update_mode 'summed' with fusion {params.fusion.value!r} has no compiled twin"
    return None


def _params_refusal(params: CLParams) -> str | None:
    """The options' part of :func:`kernel_refusal`, kept for the last ``params`` object (a
    frozen dataclass: a run passes the same one every step)."""
    global _last_params
    ref, refusal = _last_params
    if ref is not None and ref() is params:
        return refusal
    refusal = None
    if not fusion_strategy(params.fusion).compiled:
        refusal = f"fusion {params.fusion.value!r} has no compiled twin"
    for stage in active_stages(params):
        if refusal is None and not stage.compiled:
            refusal = f"the detector stage {stage.name!r} has no compiled twin"
        lacks = getattr(stage, "kernel_refusal", None)  # a combination its twin lacks
        if refusal is None and lacks is not None:
            refusal = lacks(params)
    for name, values in COMPILED_CHOICES.items():
        if refusal is None and getattr(params, name) not in values:
            refusal = f"{name} {getattr(params, name).value!r} has no compiled twin"
    if refusal is None:
        refusal = _summed_refusal(params)
    try:
        _last_params = (weakref.ref(params), refusal)
    except TypeError:  # not weakly referenceable: no cache
        _last_params = (None, None)
    return refusal
