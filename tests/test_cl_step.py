"""Tests of the per-robot CL step (:mod:`resloc.cl.step`): Algorithm 1's detector, event
trigger (eqs. 10-11), channel (eq. 8), update modes, cached neighbour estimates, batching."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.cl import (
    CLParams,
    LinkBatch,
    LinkMemory,
    NeighbourEstimate,
    ThresholdInnovation,
    UpdateMode,
    correct,
    event_threshold,
    predict,
)
from resloc.cl.backend import use_backend
from resloc.errors import ConfigError
from resloc.filters import ExtendedFilter, innovation, kalman_update, make_filter
from resloc.models import process_noise, range_bearing

FILTERS = {"ckf": make_filter("ckf"), "ukf": make_filter("ukf"), "ekf": ExtendedFilter()}
PARAMS = CLParams(range_std=0.05, bearing_std=0.03)  # noise large enough for stable tests


def make_world(seed: int, B: int = 5, links_per_robot=(2, 0, 3, 1, 2), outlier_rows=()):
    """Robots of one batch observing each other.

    Returns estimates ``x, P`` (B,), the truth, and a :class:`LinkBatch` (sorted by i, then
    j) whose neighbour estimates are the other robots' estimates.
    """
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(0, 6, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    sd = rng.uniform(0.02, 0.1, B)
    x = truth + sd[:, None] * rng.normal(size=(B, 3))
    x[:, 2] = wrap_angle(x[:, 2])
    P = (sd**2)[:, None, None] * np.eye(3) + 1e-4 * np.eye(3)
    ii, jj = [], []
    for i in range(B):
        others = np.setdiff1d(np.arange(B), [i])
        nb = np.sort(rng.choice(others, links_per_robot[i % len(links_per_robot)], False))
        ii += [i] * len(nb)
        jj += list(nb)
    i_arr, j_arr = np.array(ii, dtype=int), np.array(jj, dtype=int)
    z = range_bearing(truth[i_arr], truth[j_arr]) + rng.normal(size=(len(i_arr), 2)) * [
        PARAMS.range_std,
        PARAMS.bearing_std,
    ]
    for r in outlier_rows:
        z[r, 0] += 5.0
    z[:, 1] = wrap_angle(z[:, 1])
    links = LinkBatch(
        i=i_arr,
        j=j_arr,
        z=z,
        x_nb=x[j_arr].copy(),
        P_nb=P[j_arr].copy(),
        channel_ok=np.ones(len(i_arr), dtype=bool),
        risk_s=rng.uniform(0.0, 0.5, B),
        risk_c=rng.uniform(0.0, 0.5, B),
        lambda2=rng.uniform(0.5, 2.0, B),
    )
    return x, P, truth, links


def sub_links(links: LinkBatch, rows, robot: int | None = None) -> LinkBatch:
    """Rows of a LinkBatch; with ``robot``, as a batch of size 1 (observer index 0)."""
    rows = np.asarray(rows, dtype=int)
    if robot is None:
        return LinkBatch(
            links.i[rows], links.j[rows], links.z[rows], links.x_nb[rows], links.P_nb[rows],
            links.channel_ok[rows], links.risk_s, links.risk_c, links.lambda2,
        )  # fmt: skip
    sl = slice(robot, robot + 1)
    return LinkBatch(
        np.zeros(len(rows), dtype=int), links.j[rows], links.z[rows], links.x_nb[rows],
        links.P_nb[rows], links.channel_ok[rows], links.risk_s[sl], links.risk_c[sl],
        links.lambda2[sl],
    )  # fmt: skip


def single_update(filt, x, P, x_j, P_j, z, R):
    """One Kalman update of one robot (B = 1) from one link, by the filter primitives."""
    m = filt.relative_moments(x, P, x_j[None], P_j[None], R)
    return kalman_update(x, P, innovation(z[None], m.z_hat), m)


# --------------------------------------------------------------------------------------
# predict
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(FILTERS))
def test_predict_uses_process_noise(name: str) -> None:
    x, P, _, _ = make_world(0)
    u = np.column_stack([np.linspace(-0.5, 1.0, 5), np.linspace(-1.0, 1.0, 5)])
    filt = FILTERS[name]
    with use_backend("numpy"):  # the specification; tests/test_kernels_predict.py: its twin
        xp, Pp = predict(filt, x, P, u, 0.1, PARAMS)
    Q = process_noise(x, 0.1, np.asarray(PARAMS.odometry_std), np.asarray(PARAMS.process_floor_std))
    x_ref, P_ref = filt.predict(x, P, u, 0.1, Q)
    np.testing.assert_array_equal(xp, x_ref)
    np.testing.assert_array_equal(Pp, P_ref)


# --------------------------------------------------------------------------------------
# Detector, trigger, channel
# --------------------------------------------------------------------------------------
def test_detector_discards_and_counts_outliers() -> None:
    x, P, _, links = make_world(1, outlier_rows=(0, 3))
    params = replace(PARAMS, trigger=False, rho=1.0)
    filt = FILTERS["ckf"]
    x1, P1, out = correct(filt, x, P, links, params)
    expected = np.zeros(len(links), dtype=bool)
    expected[[0, 3]] = True
    np.testing.assert_array_equal(out.detected, expected)
    assert int(out.detected.sum()) == 2
    assert np.all(out.norm[expected] > 1.0)
    assert np.all(out.norm[~expected] <= 1.0)
    np.testing.assert_array_equal(out.fused, ~expected)
    np.testing.assert_array_equal(out.triggered, ~expected)
    assert np.all(np.isnan(out.threshold[expected]))
    assert np.all(np.isfinite(out.threshold[~expected]))
    # Same result as never having had the outlier links at all.
    keep = np.flatnonzero(~expected)
    x2, P2, _ = correct(filt, x, P, sub_links(links, keep), params)
    np.testing.assert_allclose(x1, x2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-14)
    # Detector off: the outliers are fused.
    _, _, out_off = correct(filt, x, P, links, replace(params, detector=False))
    assert not out_off.detected.any()
    assert out_off.fused.all()


def test_trigger_off_delivers_every_accepted_link() -> None:
    x, P, _, links = make_world(2, outlier_rows=(1,))
    # A threshold so large the trigger would never fire if it were on.
    params = replace(PARAMS, trigger=False, alpha=1e9, rho=1.0)
    _, _, out = correct(FILTERS["ukf"], x, P, links, params)
    np.testing.assert_array_equal(out.triggered, ~out.detected)
    np.testing.assert_array_equal(out.delivered, ~out.detected)
    np.testing.assert_array_equal(out.fused, ~out.detected)
    assert out.detected.sum() == 1
    _, _, out_on = correct(FILTERS["ukf"], x, P, links, replace(params, trigger=True))
    assert not out_on.triggered.any()


def test_channel_failure_triggers_but_does_not_update() -> None:
    """Eq. (8): a triggered transmission that does not get through (sigma_ij = 0) gives no
    update; the other links of the same robot still do."""
    x, P, _, links = make_world(3, links_per_robot=(2,))
    links.channel_ok[:] = True
    links.channel_ok[links.i == 2] = False  # robot 2 is jammed
    params = replace(PARAMS, trigger=False)
    x1, P1, out = correct(FILTERS["ckf"], x, P, links, params)
    jam = links.i == 2
    assert out.triggered[jam].all()
    assert not out.delivered[jam].any()
    assert not out.fused[jam].any()
    np.testing.assert_array_equal(x1[2], x[2])
    np.testing.assert_array_equal(P1[2], P[2])
    assert out.fused[~jam].all()
    assert np.all(np.abs(x1[[0, 1, 3, 4]] - x[[0, 1, 3, 4]]).max(axis=1) > 0)
    # With the trigger on and a zero threshold (risk factor clipped to 0): still triggered.
    links.risk_s[:] = 1.0
    links.risk_c[:] = 1.0
    x2, _, out2 = correct(FILTERS["ckf"], x, P, links, PARAMS)
    np.testing.assert_array_equal(out2.threshold[~out2.detected], 0.0)
    assert out2.triggered[jam & ~out2.detected].all()
    assert not out2.delivered[jam].any()
    np.testing.assert_array_equal(x2[2], x[2])


def test_threshold_and_trigger_follow_eq_11() -> None:
    x, P, _, links = make_world(4)
    params = replace(PARAMS, rho=np.inf, alpha=0.1)
    _, _, out = correct(FILTERS["ekf"], x, P, links, params)
    i = links.i
    delta = event_threshold(
        params.alpha, links.lambda2[i], params.gamma, out.norm, params.zeta_s,
        links.risk_s[i], params.zeta_c, links.risk_c[i],
    )  # fmt: skip
    np.testing.assert_allclose(out.threshold, delta, rtol=1e-14)
    np.testing.assert_array_equal(out.triggered, out.norm > delta)
    assert 0 < out.triggered.sum() < len(links)  # a mixed case, not all or nothing


def test_empty_link_batch() -> None:
    x, P, _, links = make_world(5)
    x1, P1, out = correct(FILTERS["ckf"], x, P, sub_links(links, []), PARAMS)
    np.testing.assert_array_equal(x1, x)
    np.testing.assert_array_equal(P1, P)
    assert len(out.norm) == 0


# --------------------------------------------------------------------------------------
# Update modes
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(FILTERS))
def test_sequential_equals_one_link_at_a_time(name: str) -> None:
    """Sequential mode = one ``correct`` call per link, in ascending neighbour order, each
    from the estimate the previous one produced (detector and trigger on)."""
    filt = FILTERS[name]
    x, P, _, links = make_world(6, links_per_robot=(3, 4, 2, 1, 3), outlier_rows=(2,))
    params = replace(PARAMS, rho=1.0, alpha=0.05)
    x1, P1, out = correct(filt, x, P, links, params)
    assert out.fused.sum() >= 5
    assert out.detected.sum() == 1
    x2, P2 = x.copy(), P.copy()
    for r in range(len(links)):  # rows are sorted by (i, j)
        xr, Pr, o = correct(filt, x2, P2, sub_links(links, [r]), params)
        x2, P2 = xr, Pr
        assert o.fused[0] == out.fused[r]
        assert o.norm[0] == pytest.approx(out.norm[r], rel=1e-12)
    np.testing.assert_allclose(x1, x2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12)
    # ...and by the filter primitives directly for robot 1 (4 neighbours, all fused here).
    xr, Pr = x[1:2], P[1:2]
    for r in np.flatnonzero((links.i == 1) & out.fused):
        xr, Pr = single_update(filt, xr, Pr, links.x_nb[r], links.P_nb[r], links.z[r], PARAMS.R)
    np.testing.assert_allclose(x1[1:2], xr, atol=1e-12)
    np.testing.assert_allclose(P1[1:2], Pr, atol=1e-12)


@pytest.mark.parametrize("name", list(FILTERS))
def test_summed_mode_is_sum_of_gains_at_the_prior(name: str) -> None:
    """Algorithm 1 literally: ``x + sum_j K_ij Lambda_ij`` and ``P - sum_j K_ij S_ij
    K_ij^T`` with every gain computed at the predicted estimate. (Weak measurements, so the
    summed covariance stays positive definite and no repair interferes.)"""
    filt = FILTERS[name]
    x, P, _, links = make_world(7, links_per_robot=(3, 2, 2, 1, 2))
    params = replace(
        PARAMS, range_std=0.5, bearing_std=0.3, trigger=False, detector=False,
        update_mode=UpdateMode.SUMMED,
    )  # fmt: skip
    x1, P1, out = correct(filt, x, P, links, params)
    assert out.fused.all()
    assert out.repairs == 0
    x_exp, P_exp = x.copy(), P.copy()
    for r in range(len(links)):
        i = links.i[r]
        m = filt.relative_moments(
            x[i : i + 1], P[i : i + 1], links.x_nb[r : r + 1], links.P_nb[r : r + 1], params.R
        )
        nu = links.z[r] - m.z_hat[0]
        nu[1] = wrap_angle(nu[1])
        K = np.linalg.solve(m.S[0], m.Pxz[0].T).T
        x_exp[i] += K @ nu
        P_exp[i] -= K @ m.S[0] @ K.T
    x_exp[:, 2] = wrap_angle(x_exp[:, 2])
    np.testing.assert_allclose(x1, x_exp, rtol=0, atol=1e-12)
    np.testing.assert_allclose(P1, P_exp, rtol=1e-9, atol=1e-14)
    # It is not the sequential result (robots with >= 2 links differ).
    x_seq, _, _ = correct(filt, x, P, links, replace(params, update_mode=UpdateMode.SEQUENTIAL))
    assert np.abs(x_seq[0] - x1[0]).max() > 1e-8


def test_summed_mode_repairs_overconfident_covariances_once_per_robot() -> None:
    """Precise measurements summed at the prior over-subtract (P - sum K S K^T is not PD):
    the covariance is projected back and each robot counts as one repair."""
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(7, links_per_robot=(3, 2, 2, 1, 2))
    params = replace(PARAMS, trigger=False, detector=False, update_mode=UpdateMode.SUMMED)
    _, P1, out = correct(filt, x, P, links, params)
    counts = np.bincount(links.i, minlength=5)
    assert out.repairs == int((counts >= 2).sum()) == 4
    assert np.all(np.linalg.eigvalsh(P1)[:, 0] > 0)


def test_params_accept_choice_strings_and_reject_typos() -> None:
    p = CLParams(update_mode="summed", neighbour_estimate="cached", trigger_norm="nis")
    assert p.update_mode is UpdateMode.SUMMED
    assert p.neighbour_estimate is NeighbourEstimate.CACHED
    with pytest.raises(ConfigError, match="update_mode"):
        CLParams(update_mode="sumed")


# --------------------------------------------------------------------------------------
# Cached neighbour estimates and the per-link memory
# --------------------------------------------------------------------------------------
def test_cached_mode_needs_memory() -> None:
    x, P, _, links = make_world(8)
    with pytest.raises(ValueError, match="LinkMemory"):
        correct(FILTERS["ckf"], x, P, links, replace(PARAMS, neighbour_estimate="cached"))


def test_cached_first_contact_forces_trigger_then_uses_memory() -> None:
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(9, links_per_robot=(2,))
    params = replace(PARAMS, neighbour_estimate=NeighbourEstimate.CACHED, alpha=1e9, detector=False)
    memory = LinkMemory(5)
    # Step 1: no cache yet -> every link triggers (despite the huge threshold) and fuses
    # with the transmitted estimate.
    x1, P1, out1 = correct(filt, x, P, links, params, memory)
    assert out1.triggered.all()
    assert out1.delivered.all()
    # (With current estimates the same huge threshold silences every link.)
    _, _, out_cur = correct(filt, x, P, links, replace(params, neighbour_estimate="current"))
    assert not out_cur.triggered.any()
    x_trig_off, P_trig_off, _ = correct(
        filt, x, P, links, replace(params, neighbour_estimate="current", trigger=False)
    )
    np.testing.assert_allclose(x1, x_trig_off, atol=1e-14)
    np.testing.assert_allclose(P1, P_trig_off, atol=1e-14)
    assert len(memory) == len(links)
    found, pos = memory.lookup(links.i, links.j)
    assert found.all()
    np.testing.assert_array_equal(memory.x[pos], links.x_nb)
    np.testing.assert_array_equal(memory.P[pos], links.P_nb)

    # Step 2: neighbours moved on (new transmitted estimates); the trigger compares with
    # the cached estimate and stays silent: no update at all.
    links2 = sub_links(links, np.arange(len(links)))
    links2.x_nb = links.x_nb + np.array([0.3, -0.2, 0.1])
    x2, P2, out2 = correct(filt, x1, P1, links2, params, memory)
    assert not out2.triggered.any()
    np.testing.assert_array_equal(x2, x1)
    np.testing.assert_array_equal(P2, P1)
    # The norm is the innovation against the cached estimate of j, not the new one.
    m = filt.relative_moments(x1[links.i], P1[links.i], links.x_nb, links.P_nb, params.R)
    nu = innovation(links2.z, m.z_hat)
    np.testing.assert_allclose(out2.norm, np.hypot(nu[:, 0], nu[:, 1]), rtol=1e-12)
    np.testing.assert_array_equal(memory.x[pos], links.x_nb)  # nothing delivered: unchanged

    # update_without_transmission: the silent link is fused with the cached estimate.
    x3, P3, out3 = correct(
        filt, x1, P1, links2, replace(params, update_without_transmission=True), memory
    )
    assert out3.fused.all()
    assert not out3.delivered.any()
    x_exp, P_exp, _ = correct(
        filt, x1, P1, sub_links(links, np.arange(len(links))),
        replace(params, neighbour_estimate="current", trigger=False),
    )  # fmt: skip
    np.testing.assert_allclose(x3, x_exp, atol=1e-13)
    np.testing.assert_allclose(P3, P_exp, atol=1e-13)


def test_cached_delivered_link_fuses_fresh_estimate_and_refreshes_memory() -> None:
    filt = FILTERS["ukf"]
    x, P, _, links = make_world(10, links_per_robot=(1,))
    params = replace(PARAMS, neighbour_estimate=NeighbourEstimate.CACHED, detector=False)
    memory = LinkMemory(5)
    correct(filt, x, P, links, replace(params, alpha=1e9), memory)  # fills the cache
    links2 = sub_links(links, np.arange(len(links)))
    links2.x_nb = links.x_nb + np.array([0.05, 0.05, 0.0])
    # A tiny threshold: everything triggers; the update uses the transmitted estimate.
    small = replace(params, alpha=1e-9)
    x2, P2, out2 = correct(filt, x, P, links2, small, memory)
    assert out2.delivered.all()
    x_exp, P_exp, _ = correct(
        filt, x, P, links2, replace(small, neighbour_estimate="current", trigger=False)
    )
    np.testing.assert_allclose(x2, x_exp, atol=1e-13)
    np.testing.assert_allclose(P2, P_exp, atol=1e-13)
    _, pos = memory.lookup(links.i, links.j)
    np.testing.assert_array_equal(memory.x[pos], links2.x_nb)


def test_cached_jammed_first_contact_stays_unknown() -> None:
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(11, links_per_robot=(1,))
    links.channel_ok[:] = False
    params = replace(PARAMS, neighbour_estimate="cached", alpha=1e9, detector=False)
    memory = LinkMemory(5)
    _, _, out = correct(filt, x, P, links, params, memory)
    assert out.triggered.all()
    assert not out.delivered.any()
    assert len(memory) == 0


def test_last_sent_threshold_uses_memory() -> None:
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(12, links_per_robot=(2,))
    params = replace(
        PARAMS, threshold_innovation=ThresholdInnovation.LAST_SENT, rho=np.inf, trigger=False
    )
    memory = LinkMemory(5)
    _, _, out1 = correct(filt, x, P, links, params, memory)
    i = links.i
    base = (
        params.alpha
        / links.lambda2[i]
        * (1 - params.zeta_s * links.risk_s[i] - params.zeta_c * links.risk_c[i])
    )
    np.testing.assert_allclose(out1.threshold, base, rtol=1e-14)  # nothing sent before
    _, _, out2 = correct(filt, x, P, links, params, memory)
    np.testing.assert_allclose(out2.threshold, base * (1 + params.gamma * out1.norm), rtol=1e-14)


def test_link_memory_store_and_lookup() -> None:
    mem = LinkMemory(10)
    found, _ = mem.lookup(np.array([1]), np.array([2]))
    assert not found.any()
    i, j = np.array([3, 1, 1]), np.array([0, 7, 2])
    xs = np.arange(9.0).reshape(3, 3)
    Ps = np.stack([k * np.eye(3) for k in (1.0, 2.0, 3.0)])
    mem.store(i, j, xs, Ps, np.array([0.1, 0.2, 0.3]))
    assert len(mem) == 3
    assert np.all(np.diff(mem.keys) > 0)
    found, pos = mem.lookup(np.array([1, 3, 2, 1]), np.array([2, 0, 2, 7]))
    np.testing.assert_array_equal(found, [True, True, False, True])
    np.testing.assert_array_equal(mem.x[pos[[0, 1, 3]]], xs[[2, 0, 1]])
    np.testing.assert_array_equal(mem.last_norm[pos[[0, 1, 3]]], [0.3, 0.1, 0.2])
    # Overwrite one, add one.
    mem.store(np.array([1, 9]), np.array([7, 9]), -xs[:2], Ps[:2], np.array([5.0, 6.0]))
    assert len(mem) == 4
    found, pos = mem.lookup(np.array([1, 9, 3]), np.array([7, 9, 0]))
    assert found.all()
    np.testing.assert_array_equal(mem.x[pos], [-xs[0], -xs[1], xs[0]])
    np.testing.assert_array_equal(mem.last_norm[pos], [5.0, 6.0, 0.1])


# --------------------------------------------------------------------------------------
# Batching: one big call = one call per robot; per-robot parameters
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", list(UpdateMode))
@pytest.mark.parametrize("name", list(FILTERS))
def test_batch_equals_per_robot_calls(name: str, mode: UpdateMode) -> None:
    filt = FILTERS[name]
    x, P, _, links = make_world(13, links_per_robot=(2, 0, 3, 1, 4), outlier_rows=(3,))
    links.channel_ok[[1, 5]] = False
    params = replace(PARAMS, rho=1.0, alpha=0.05, update_mode=mode)
    xb, Pb, out = correct(filt, x, P, links, params)
    assert out.detected.sum() == 1
    assert 0 < out.fused.sum() < len(links)
    for b in range(5):
        rows = np.flatnonzero(links.i == b)
        x1, P1, o1 = correct(filt, x[b : b + 1], P[b : b + 1], sub_links(links, rows, b), params)
        np.testing.assert_allclose(x1[0], xb[b], rtol=0, atol=1e-12)
        np.testing.assert_allclose(P1[0], Pb[b], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(o1.fused, out.fused[rows])
        np.testing.assert_array_equal(o1.triggered, out.triggered[rows])
        np.testing.assert_array_equal(o1.detected, out.detected[rows])
        np.testing.assert_allclose(o1.norm, out.norm[rows], rtol=1e-12)


def test_batch_equals_per_robot_calls_cached() -> None:
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(14, links_per_robot=(2, 1, 3, 0, 2))
    params = replace(PARAMS, neighbour_estimate="cached", alpha=0.05, rho=np.inf)
    mem_all = LinkMemory(5)
    mems = [LinkMemory(5) for _ in range(5)]
    for step in range(3):
        links.x_nb = links.x_nb + 0.05 * step
        xb, Pb, out = correct(filt, x, P, links, params, mem_all)
        for b in range(5):
            rows = np.flatnonzero(links.i == b)
            lb = sub_links(links, rows, b)
            x1, P1, o1 = correct(filt, x[b : b + 1], P[b : b + 1], lb, params, mems[b])
            np.testing.assert_allclose(x1[0], xb[b], atol=1e-12)
            np.testing.assert_allclose(P1[0], Pb[b], atol=1e-12)
            np.testing.assert_array_equal(o1.triggered, out.triggered[rows])
        x, P = xb, Pb


def test_per_robot_array_parameters() -> None:
    """``rho``, ``alpha``, ``gamma``, ``zeta_s``, ``zeta_c`` as arrays of shape (B,): each
    robot behaves as with its own scalar."""
    filt = FILTERS["ckf"]
    x, P, _, links = make_world(15, links_per_robot=(2, 3, 2, 2, 1))
    rho = np.array([np.inf, 1e-9, np.inf, 0.5, np.inf])
    alpha = np.array([0.3, 0.3, 1e-6, 0.1, 1e6])
    gamma = np.array([0.5, 0.0, 1.0, 2.0, 0.5])
    zeta_s = np.array([0.5, 0.1, 0.9, 0.0, 0.5])
    params = replace(PARAMS, rho=rho, alpha=alpha, gamma=gamma, zeta_s=zeta_s)
    xb, Pb, out = correct(filt, x, P, links, params)
    assert out.detected[links.i == 1].all()  # rho ~ 0: robot 1 discards everything
    assert not out.detected[links.i == 0].any()
    assert out.triggered[links.i == 2].all()  # alpha ~ 0: robot 2 always transmits
    assert not out.triggered[links.i == 4].any()  # alpha huge: robot 4 never does
    for b in range(5):
        pb = replace(
            PARAMS, rho=float(rho[b]), alpha=float(alpha[b]), gamma=float(gamma[b]),
            zeta_s=float(zeta_s[b]),
        )  # fmt: skip
        x1, P1, o1 = correct(filt, x, P, links, pb)
        rows = links.i == b
        np.testing.assert_allclose(xb[b], x1[b], atol=1e-14)
        np.testing.assert_allclose(Pb[b], P1[b], atol=1e-14)
        np.testing.assert_array_equal(out.detected[rows], o1.detected[rows])
        np.testing.assert_array_equal(out.triggered[rows], o1.triggered[rows])
        np.testing.assert_allclose(out.threshold[rows], o1.threshold[rows], rtol=1e-14)


def test_clparams_has_no_unused_catch_all_field() -> None:
    """Every CLParams field is an option the step reads; a free-form dict is not."""
    with pytest.raises(TypeError):
        CLParams(extra={"rho": 0.1})
