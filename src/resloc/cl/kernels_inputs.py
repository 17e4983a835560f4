"""The compiled link loop's inputs: their named structures, the checks of the indices the
loop reads without checking, and the per-link rows of ``cached`` neighbour estimates.

:func:`resloc.cl.kernels.fast_correct` builds the structures each step
(:class:`KernelOptions` once per ``params``: :mod:`resloc.cl.kernels_prepared`) and calls
the loop with their plain forms (:mod:`resloc.cl.kernels_plain`); the kernels read the
fields by position, in the order below.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.kernels_checks import observer_bound
from resloc.cl.kernels_plain import contiguous
from resloc.cl.links import LinkBatch

__all__ = [
    "KernelLinks",
    "KernelOptions",
    "KernelOutputs",
    "KernelRobots",
    "cached_rows",
    "pair_warm_up_batch",
    "shapes_ok",
]


class KernelLinks(NamedTuple):
    """Per-link inputs, each with leading axis E (rows sorted by observer)."""

    i: np.ndarray  # (E,) int64 observers
    z: np.ndarray  # (E, 2) measured range, bearing
    x_nb: np.ndarray  # (S, 3) transmitted estimates: link e's is row nb[e]
    P_nb: np.ndarray  # (S, 3, 3)
    nb: np.ndarray  # (E,) int64 row of x_nb / P_nb (LinkBatch.neighbour_rows)
    channel_ok: np.ndarray  # (E,) bool
    last_norm: np.ndarray  # (E,) last delivered norm (``last_sent``), else (0,)
    x_ref: np.ndarray  # (E, 3) the estimate of j the moments use (cached or x_nb)
    P_ref: np.ndarray  # (E, 3, 3)
    known: np.ndarray  # (E,) bool: j's estimate received before (``cached``)


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
    cached: bool  # neighbour estimates: the last received (else the transmitted one)
    update_without_transmission: bool


class KernelOutputs(NamedTuple):
    """Per-link decisions, written by the kernel."""

    norm: np.ndarray  # (E,)
    threshold: np.ndarray  # (E,)
    flags: np.ndarray  # (5, E) bool: detected, triggered, delivered, fused, repaired


_NO_ROWS = np.zeros(0, np.int64)


def _shape(a) -> tuple:
    """``np.shape(a)`` without its dispatch for an array (a third of a microsecond each)."""
    return a.shape if type(a) is np.ndarray else np.shape(a)


def shapes_ok(x, P, links: LinkBatch, li, lj, robots: KernelRobots, neighbours) -> bool:
    """Every index the kernel will use is in range (the compiled loop does not check), and
    no link repeats the one before it. ``li``, ``lj``: the links' observers and observed
    nodes as contiguous int64 arrays."""
    E = len(li)
    nb, x_nb, P_nb = neighbours
    S = len(x_nb)
    if nb is not None:
        if not isinstance(nb, np.ndarray) or nb.shape != (E,) or nb.dtype.kind not in "iu":
            return False
        nb = contiguous(nb, np.int64)
    B = observer_bound(li, lj, _NO_ROWS if nb is None else nb, S)
    x_shape, P_shape = _shape(x), _shape(P)
    if B < 1 or len(x_shape) != 2 or len(P_shape) != 3 or x_shape[0] < B or P_shape[0] < B:
        return False
    if x_shape[1] != 3 or P_shape[1:] != (3, 3):
        return False
    if _shape(x_nb) != (S, 3) or _shape(P_nb) != (S, 3, 3) or (nb is None and S != E):
        return False
    if _shape(links.z) != (E, 2) or _shape(links.channel_ok) != (E,) or _shape(links.j) != (E,):
        return False
    for a in robots[:3]:  # risks and lambda2: every observer's
        if a.ndim != 1 or len(a) < B:
            return False
    for a in robots[3:]:  # gains: one, or every observer's
        if a.shape[0] != 1 and a.shape[0] < B:
            return False
    return True


def cached_rows(memory, li, lj, nb, x_nb, P_nb, last_sent: bool):
    """The per-link inputs of ``cached`` neighbour estimates
    (:meth:`~resloc.cl.memory.LinkMemory.cached_rows`, one compiled pass): the transmitted
    estimates per link ``(E, 3)``, ``(E, 3, 3)``, the estimates the moments use (j's last
    received where robot i has one, else the transmitted: twin ``resloc.cl.step._decide``),
    whether there is one ``(E,)`` and, with ``last_sent``, the last delivered norms
    ``(E,)`` (else ``(0,)``)."""
    rows = np.arange(len(li), dtype=np.int64) if nb is None else contiguous(nb, np.int64)
    return memory.cached_rows(li, lj, rows, contiguous(x_nb), contiguous(P_nb), last_sent)


def pair_warm_up_batch() -> tuple[np.ndarray, np.ndarray, LinkBatch]:
    """``(x (2, 3), P (2, 3, 3), links)``: two robots observing each other, the
    smallest batch that runs a correction's compiled forms once (the warm-ups of
    :func:`resloc.cl.kernels.warm_up` and :func:`resloc.cl.kernels_joint.warm_up_joint_form`
    call it before a run times its steps)."""
    x = np.array([[0.0, 0.0, 0.1], [1.0, 0.5, -0.2]])
    P = np.broadcast_to(0.01 * np.eye(3), (2, 3, 3)).copy()
    links = LinkBatch(
        np.array([0, 1]), np.array([1, 0]), np.array([[1.1, 0.4], [1.1, 2.9]]),
        x[[1, 0]], P[[1, 0]], np.array([True, True]), np.zeros(2), np.zeros(2), np.ones(2),
    )  # fmt: skip
    return x, P, links
