"""Compiled twin of the stealthy attacker's tamper hook (``stealthy_tamper``).

The stealthy attacker sees the victim's predicted measurement ``hat z_ij`` and innovation
covariance ``S`` of each link, so it acts inside the correction, between the moments and the
detector. Its hook (``LinkBatch.tamper``) carries a plain-data description of itself,
:class:`KernelTamper` (``tamper.kernel_form``); the CL kernel (:mod:`resloc.cl.kernels`)
then computes the falsified measurement of every attacked link in its link loop
(:func:`stealthy_measurement`) instead of calling Python. A hook without ``kernel_form``
keeps the reference path (:func:`resloc.cl.backend.kernel_refusal` says so).

================================  =======================================================
kernel function                   numpy twin (:mod:`resloc.world.adversary`)
================================  =======================================================
:func:`_largest_stealthy_step`    :func:`~resloc.world.adversary.largest_stealthy_step`
:func:`_largest_linear_step`      :func:`~resloc.world.adversary.largest_linear_step`
:func:`stealthy_measurement`     the hook of :func:`~resloc.world.adversary.stealthy_tamper`
                                  (with :func:`resloc.world.attacks.apply_injection`)
================================  =======================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl.backend import HAVE_NUMBA
from resloc.cl.kernels_math import gain_array

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    _jit_inline = numba.njit(cache=True, nogil=True, inline="always")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit_inline(func):
        return func


__all__ = ["KernelTamper", "kernel_tamper", "no_tamper"]


class KernelTamper(NamedTuple):
    """The stealthy attacker of one step as the kernel takes it.

    Gains are ``(1,)`` or ``(B,)`` (per observer). Norm codes as
    :data:`resloc.cl.kernels_detection.NORM_CODE`.
    """

    on: bool
    z: np.ndarray  # (E, 2) the honest measurements of the step
    observer: np.ndarray  # (E,) int64 robot i of each link (must be the LinkBatch's i)
    attacked: np.ndarray  # (E,) bool, the links the attacker controls this step
    direction: np.ndarray  # (2,) unit injection direction
    margin: float
    cap: float  # the largest physically injectable step along the direction
    detector: bool  # the victim runs the gate
    norm: int  # the gate's norm code
    rho: np.ndarray  # (1,) or (B,)
    noise_std: np.ndarray  # (2,)
    cusum: bool  # keep NIS <= margin k (full knowledge of a NIS CUSUM)
    cusum_k: np.ndarray
    mean_cusum: bool  # keep |w_c| <= margin k_m (full knowledge of the mean-shift CUSUM)
    mean_cusum_k: np.ndarray


def no_tamper() -> KernelTamper:
    """No attacker in the kernel (the measurements as given)."""
    one = np.zeros(1)
    return KernelTamper(
        False, np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.bool_), np.zeros(2),
        0.0, 0.0, False, 0, one, np.ones(2), False, one, False, one,
    )  # fmt: skip


def kernel_tamper(
    z, attacked, observer, direction, margin, cap, detector, norm_code, rho, noise_std,
    cusum_k, mean_cusum_k,
) -> KernelTamper:  # fmt: skip
    """A :class:`KernelTamper` from the stealthy attacker's parameters (those of
    :func:`resloc.world.adversary.stealthy_tamper`, already normalized: unit ``direction``,
    ``cusum_k`` / ``mean_cusum_k`` None when the attacker does not keep under them)."""
    one = np.zeros(1)
    return KernelTamper(
        True,
        np.ascontiguousarray(z, dtype=float),
        np.ascontiguousarray(observer, dtype=np.int64),
        np.ascontiguousarray(attacked, dtype=np.bool_),
        np.ascontiguousarray(direction, dtype=float),
        float(margin),
        float(cap),
        bool(detector),
        int(norm_code),
        gain_array(rho),
        np.ascontiguousarray(noise_std, dtype=float),
        cusum_k is not None,
        one if cusum_k is None else gain_array(cusum_k),
        mean_cusum_k is not None,
        one if mean_cusum_k is None else gain_array(mean_cusum_k),
    )


@_jit_inline
def _largest_stealthy_step(nu0, nu1, d0, d1, w00, w01, w10, w11, c2):
    """Largest ``a >= 0`` with ``(nu + a d)^T W (nu + a d) <= c2`` (0 when the honest
    innovation already violates it). Twin: ``largest_stealthy_step``."""
    wd0 = w00 * d0 + w01 * d1
    wd1 = w10 * d0 + w11 * d1
    qa = wd0 * d0 + wd1 * d1
    qb = wd0 * nu0 + wd1 * nu1
    qc = nu0 * (w00 * nu0 + w01 * nu1) + nu1 * (w10 * nu0 + w11 * nu1) - c2
    if not (qc <= 0.0 and qa > 0.0):
        return 0.0
    disc = qb * qb - qa * qc
    root = (-qb + math.sqrt(disc if disc > 0.0 else 0.0)) / qa
    return root if root > 0.0 else 0.0


@_jit_inline
def _largest_linear_step(w0, w1, v0, v1, c):
    """Largest ``a >= 0`` with ``|w_k + a v_k| <= c`` for both components (0 when the honest
    value already violates one). Twin: ``largest_linear_step``."""
    if not (abs(w0) <= c and abs(w1) <= c):
        return 0.0
    hi = _linear_bound(w0, v0, c)
    other = _linear_bound(w1, v1, c)
    if other < hi:
        hi = other
    return hi if hi > 0.0 else 0.0


@_jit_inline
def _linear_bound(w, v, c):
    """Largest ``a`` with ``|w + a v| <= c`` (``inf`` when ``v = 0``)."""
    if v > 0.0:
        return (c - w) / v
    if v < 0.0:
        return (-c - w) / v
    return math.inf


@_jit_inline
def _at(gain, i):
    return gain[i] if gain.shape[0] > 1 else gain[0]


@_jit_inline
def stealthy_measurement(tamper, i, z0, z1, nu0, nu1, l00, l10, l11):
    """The measurement robot ``i`` receives on an attacked link (honest ``z``, innovation
    ``nu`` against the victim's prediction, ``S = L L^T``): ``z + a d`` with the largest
    ``a`` every known test lets through (:func:`resloc.world.adversary.stealthy_tamper`),
    range kept >= 0; the caller wraps the bearing."""
    (_on, _z, _obs, _attacked, d, margin, cap, detector, norm, rho, std, cusum, ck, mean, mk) = (
        tamper
    )
    d0 = d[0]
    d1 = d[1]
    # W = S^-1 by the Cholesky solve of the unit vectors (the order of solve_spd)
    y0 = 1.0 / l00
    w10 = (0.0 - l10 * y0) / l11 / l11
    w00 = (y0 - l10 * w10) / l00
    w11 = (1.0 / l11) / l11
    w01 = (0.0 - l10 * w11) / l00
    a = cap
    if detector:
        c = margin * _at(rho, i)
        if norm == 0:
            s = _largest_stealthy_step(nu0, nu1, d0, d1, 1.0, 0.0, 0.0, 1.0, c * c)
        elif norm == 1:
            m00 = 1.0 / std[0] ** 2
            m11 = 1.0 / std[1] ** 2
            s = _largest_stealthy_step(nu0, nu1, d0, d1, m00, 0.0, 0.0, m11, c * c)
        else:
            s = _largest_stealthy_step(nu0, nu1, d0, d1, w00, w01, w10, w11, c * c)
        if s < a:
            a = s
    if cusum:
        s = _largest_stealthy_step(nu0, nu1, d0, d1, w00, w01, w10, w11, margin * _at(ck, i))
        if s < a:
            a = s
    if mean:
        w0 = nu0 / l00
        w1 = (nu1 - l10 * w0) / l11
        v0 = d0 / l00
        v1 = (d1 - l10 * v0) / l11
        s = _largest_linear_step(w0, w1, v0, v1, margin * _at(mk, i))
        if s < a:
            a = s
    if not math.isfinite(a):
        a = 0.0
    return abs(z0 + a * d0), z1 + a * d1  # the caller wraps the bearing
