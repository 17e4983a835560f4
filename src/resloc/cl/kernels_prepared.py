"""What a compiled correction takes from its parameters alone, prepared once per ``params``
object (a frozen dataclass: a run passes the same object every step), and whether the
compiled path runs the step at all (:func:`~resloc.cl.backend.kernel_refusal`), kept per
filter; for :func:`resloc.cl.kernels.fast_correct`.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np

from resloc.cl.backend import backend, kernel_refusal
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_bookkeeping import COMPILED_BOOKKEEPING, CompiledBookkeeping
from resloc.cl.kernels_detection import NORM_CODE
from resloc.cl.kernels_inputs import KernelOptions
from resloc.cl.kernels_plain import contiguous, plain
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation
from resloc.linalg import JITTER_LEVELS

__all__ = ["Prepared", "prepared_for", "refusal"]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)


def _per_robot(v) -> np.ndarray:
    """A scalar or per-robot gain as a contiguous float array of shape (1,) or (B,)."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(v, dtype=float)).ravel())


class Prepared(NamedTuple):
    """What a correction takes from ``params`` alone (a frozen dataclass: a run passes the
    same object every step), prepared once."""

    gains: tuple[np.ndarray, ...]  # rho, alpha, gamma, zeta_s, zeta_c: (1,) or (B,)
    options: KernelOptions
    strategy: object  # the fusion method's FusionStrategy
    problem: str | None  # why the strategy cannot run with params
    bookkeeping: CompiledBookkeeping
    last_sent: bool
    cached: bool
    plain_options: tuple  # options as the kernel is called with it (kernels_plain.plain)


_last_prepared: tuple = (None, None)


def prepared_for(params: CLParams) -> Prepared:
    """The gains, options and fusion strategy of ``params`` as the kernel takes them, kept
    for the last ``params`` object."""
    global _last_prepared
    ref, kept = _last_prepared
    if ref is not None and ref() is params:
        return kept
    gains = params.rho, params.alpha, params.gamma, params.zeta_s, params.zeta_c
    last_sent = params.threshold_innovation is ThresholdInnovation.LAST_SENT
    cached = params.neighbour_estimate is NeighbourEstimate.CACHED
    options = KernelOptions(
        contiguous(params.R),
        contiguous(params.noise_std),
        bool(params.detector),
        bool(params.trigger),
        NORM_CODE[params.detector_norm],
        NORM_CODE[params.trigger_norm],
        float(params.risk_factor_floor),
        last_sent,
        _JITTER,
        cached,
        bool(params.update_without_transmission),
    )
    strategy = fusion_strategy(params.fusion)
    kept = Prepared(
        tuple(_per_robot(g) for g in gains),
        options,
        strategy,
        strategy.problem(params),
        COMPILED_BOOKKEEPING[strategy.kernel_bookkeeping],
        last_sent,
        cached,
        plain(options),
    )
    try:
        _last_prepared = (weakref.ref(params), kept)
    except TypeError:  # not weakly referenceable: no cache
        _last_prepared = (None, None)
    return kept


#: Per filter (a run's estimators alternate): the last ``params``, key and refusal.
_refusals: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def refusal(filt, params: CLParams, links: LinkBatch) -> str | None:
    """:func:`~resloc.cl.backend.kernel_refusal`, kept per filter for its last ``params``,
    backend and the links' optional fields it reads (whether there is a tamper hook and
    whether it has a compiled form, whether there are transmitted independent parts)."""
    tamper = links.tamper
    form = 0 if tamper is None else 1 + (getattr(tamper, "kernel_form", None) is None)
    key = (backend(), form, links.P_nb_ind is None, links.z_reciprocal is None)
    try:
        params_ref, last_key, kept = _refusals[filt]
        if last_key == key and params_ref() is params:
            return kept
    except (KeyError, TypeError):
        pass
    kept = kernel_refusal(filt, params, links)
    try:
        _refusals[filt] = (weakref.ref(params), key, kept)
    except TypeError:  # not hashable or weakly referenceable: no cache
        pass
    return kept
