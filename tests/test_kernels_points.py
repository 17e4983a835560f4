"""The sigma points' stage of the row-order link loop (:mod:`resloc.cl.kernels_points`):
the moments of ``z_ij`` from the SIMD polynomials, with libm for the points outside their
range, against the numpy reference (``SigmaPointFilter.relative_moments``) to 1e-9, on
ordinary links and on the special points (a neighbour at the robot's position, headings
beyond 2 pi, heading offsets beyond the polynomials' range); and the whole correction in
row order with those links, compiled, against the reference."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.cl import CLParams, LinkBatch, kernels
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import filter_kernel_spec
from resloc.filters import SigmaPointFilter, make_filter
from resloc.filters.base import FilterKind
from resloc.filters.sigma_points import cubature_rule
from resloc.linalg import cholesky_jitter
from test_engine import assert_equivalent, run_both

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ckf-arith": SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), False),
}
R = np.diag([0.02**2, 0.03**2])


def _links(case: str, E: int = 24, seed: int = 3):
    """``E`` links (one observer each) of a kind: ``ordinary``, ``same-position`` (the
    neighbour at the observer's position: a point of range 0), ``heading-beyond-2pi``
    (unwrapped headings up to 9 rad), ``wide-heading`` (a heading variance whose points turn
    by more than the polynomials' range)."""
    rng = np.random.default_rng(seed)
    x_i = np.column_stack([rng.uniform(0, 5, (E, 2)), rng.uniform(-np.pi, np.pi, E)])
    x_j = np.column_stack([rng.uniform(0, 5, (E, 2)), rng.uniform(-np.pi, np.pi, E)])
    A = rng.normal(size=(2, E, 3, 3)) * 0.1
    P_i, P_j = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(3)
    if case == "same-position":
        x_j[::2, :2] = x_i[::2, :2]
    elif case == "heading-beyond-2pi":
        x_i[:, 2] = rng.uniform(6.3, 9.0, E) * rng.choice([-1.0, 1.0], E)
    elif case == "wide-heading":
        P_i[::3, 2, 2] = 1e4
    return x_i, P_i, x_j, P_j


def _point_moments(filt, x_i, P_i, x_j, P_j):
    """The kernel's moments of every link, from the offsets of the reference's points."""
    from resloc.cl.kernels_points import POINT_ROWS, point_moments

    spec = filter_kernel_spec(filt)
    Wm, Wc, circular = spec[4], spec[5], spec[6]
    unit = filt.rule6.unit  # (m, 6)
    m = len(Wm)
    zh = np.empty((len(x_i), 2))
    S = np.empty((len(x_i), 2, 2))
    Pxz = np.empty((len(x_i), 3, 2))
    Z = np.zeros((POINT_ROWS, m))
    for e in range(len(x_i)):
        L = np.zeros((6, 6))
        L[:3, :3] = cholesky_jitter(P_i[e])
        L[3:, 3:] = cholesky_jitter(P_j[e])
        off = np.ascontiguousarray(L @ unit.T)  # (6, m)
        h = x_i[e, 2]
        zh0, zh1, s00, s01, s11 = point_moments(
            off, Wm, Wc, circular, x_i[e, 0], x_i[e, 1], h, x_j[e, 0], x_j[e, 1],
            np.sin(h), np.cos(h), R, Z, Pxz[e],
        )  # fmt: skip
        zh[e] = zh0, zh1
        S[e] = [[s00, s01], [s01, s11]]
    return zh, S, Pxz


@pytest.mark.parametrize(
    "case", ["ordinary", "same-position", "heading-beyond-2pi", "wide-heading"]
)
@pytest.mark.parametrize("name", list(FILTERS))
def test_point_moments_match_the_reference(name: str, case: str) -> None:
    from resloc.cl.kernels_points import point_moments

    assert hasattr(point_moments, "signatures"), "not the compiled function"
    filt = FILTERS[name]
    x_i, P_i, x_j, P_j = _links(case)
    zh, S, Pxz = _point_moments(filt, x_i, P_i, x_j, P_j)
    ref = filt.relative_moments(x_i, P_i, x_j, P_j, R)
    d = zh - ref.z_hat
    d[:, 1] = wrap_angle(d[:, 1])
    assert np.abs(d).max() <= 1e-9
    np.testing.assert_allclose(S, ref.S, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Pxz, ref.Pxz, rtol=0, atol=1e-9)


@pytest.mark.parametrize("case", ["same-position", "heading-beyond-2pi", "wide-heading"])
def test_row_order_correction_with_special_points_matches_the_reference(case: str) -> None:
    """The whole correction in row order (fewer links than the rounds take) on links whose
    points need libm: compiled, and equal to the reference."""
    x_i, P_i, x_j, P_j = _links(case, E=20)
    E = len(x_i)
    x = np.concatenate([x_i, x_j])
    P = np.concatenate([P_i, P_j])
    i = np.arange(E)
    j = E + i
    rng = np.random.default_rng(5)
    z = np.column_stack([rng.uniform(0.1, 3.0, E), rng.uniform(-np.pi, np.pi, E)])
    links = LinkBatch(
        i, j, z, x[j].copy(), P[j].copy(), np.ones(E, dtype=bool), np.zeros(2 * E),
        np.zeros(2 * E), np.ones(2 * E),
    )  # fmt: skip
    params = CLParams(range_std=0.02, bearing_std=0.03, rho=1e3, alpha=1e-3)
    before = rounds.LOOP_RUNS.copy()
    fast, ref = run_both(FILTERS["ckf"], x, P, links, params)
    assert rounds.LOOP_RUNS - before == {"row_order": 1}
    assert fast[2].delivered.any()
    assert_equivalent(fast, ref)
