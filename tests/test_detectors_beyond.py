"""Unit-aware detection (issue 6): NIS chi-square gate, CUSUM, per-link statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from resloc.cl.cusum import chi2_gate, cusum_alarm, cusum_update, link_cusum, nis
from resloc.cl.detector import InnovationNorm, innovation_norm
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams
from resloc.cl.step import LinkBatch, correct
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing


def test_chi2_gate_false_alarm_rate(rng):
    thr = chi2_gate(0.01)
    assert thr == pytest.approx(-2.0 * math.log(0.01))  # chi2 with 2 dof: exponential
    samples = rng.normal(size=(200_000, 2))
    S = np.broadcast_to(np.eye(2), (len(samples), 2, 2))
    rate = np.mean(nis(samples, S) > thr)
    assert rate == pytest.approx(0.01, abs=0.002)
    np.testing.assert_allclose(chi2_gate(np.array([0.1, 0.01])), chi2.isf([0.1, 0.01], 2))


def test_nis_matches_detector_norm(rng, random_spd):
    nu = rng.normal(size=(50, 2))
    S = random_spd(rng, 50, 2)
    np.testing.assert_allclose(
        np.sqrt(nis(nu, S)), innovation_norm(nu, S, InnovationNorm.NIS, np.ones(2))
    )


def test_cusum_update_and_alarm():
    g = np.zeros(3)
    g = cusum_update(g, np.array([1.0, 10.0, 100.0]), 4.0, 40.0)
    np.testing.assert_allclose(g, [0.0, 6.0, 40.0])
    np.testing.assert_array_equal(cusum_alarm(g, 20.0), [False, False, True])


def test_link_statistic_store():
    st = LinkStatistic(10)
    np.testing.assert_array_equal(st.get(np.array([1, 2]), np.array([3, 4])), [0.0, 0.0])
    st.set(np.array([2, 1]), np.array([4, 3]), np.array([5.0, 7.0]))
    np.testing.assert_array_equal(st.get(np.array([1, 2, 3]), np.array([3, 4, 3])), [7, 5, 0])
    st.set(np.array([1]), np.array([3]), np.array([1.5]))
    assert st.get(np.array([1]), np.array([3]))[0] == 1.5
    assert len(st) == 2


def test_persistent_small_bias_caught_by_cusum_not_gate(rng):
    """A bias that keeps every NIS under the gate (p_fa = 0.01) but above k trips the CUSUM."""
    store = LinkStatistic(4)
    i, j = np.array([0]), np.array([1])
    gate = chi2_gate(0.01)
    alarms = []
    for _ in range(40):
        stat = np.array([7.0])  # under the 9.2 gate, above k = 4
        assert stat[0] < gate
        alarms.append(link_cusum(store, i, j, stat, 4.0, 20.0)[0])
    assert not alarms[5] and alarms[7] and alarms[-1]
    store2 = LinkStatistic(4)
    honest = [
        link_cusum(store2, i, j, nis(rng.normal(size=(1, 2)), np.eye(2)[None]), 4.0, 20.0)[0]
        for _ in range(2000)
    ]
    assert sum(honest) == 0


def test_config_false_alarm_sets_rho_and_validates():
    sc = default_scenario().replace(**{"detector.norm": "nis", "detector.false_alarm": 0.01})
    assert sc.cl_params().rho == pytest.approx(math.sqrt(chi2.isf(0.01, 2)))
    with pytest.raises(ConfigError, match=r"detector\.false_alarm"):
        default_scenario().replace(**{"detector.false_alarm": 0.01})
    with pytest.raises(ConfigError, match=r"detector\.cusum_h"):
        default_scenario().replace(**{"detector.cusum_h": 0.0})
    with pytest.raises(ConfigError, match=r"estimator\.fusion"):
        default_scenario().replace(**{"estimator.fusion": "ci", "estimator.update_mode": "summed"})
    for fusion in ("tracked", "factorized", "gauge"):
        with pytest.raises(ConfigError, match=r"estimator\.fusion"):
            default_scenario().replace(
                **{"estimator.fusion": fusion, "estimator.neighbour_estimate": "cached"}
            )
    with pytest.raises(ConfigError, match=r"estimator\.gauge_sums"):
        default_scenario().replace(**{"estimator.gauge_sums": "gossip"})
    with pytest.raises(ConfigError, match=r"detector\.mean_cusum_k"):
        default_scenario().replace(**{"detector.mean_cusum_k": 0.0})
    p = default_scenario().replace(**{"detector.cusum": True, "detector.cusum_k": 3.0})
    assert p.cl_params().cusum and p.cl_params().cusum_k == 3.0
    assert not default_scenario().cl_params().cusum  # the paper's detector by default


def _two_robot_links(z_bias, rho, cusum):
    x = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    P = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-4]), (2, 3, 3)).copy()
    z = range_bearing(x[[0]], x[[1]]) + z_bias
    links = LinkBatch(
        np.array([0]),
        np.array([1]),
        z,
        x[[1]],
        P[[1]],
        np.array([True]),
        np.zeros(2),
        np.zeros(2),
        np.full(2, 1.0),
    )
    params = CLParams(
        detector_norm="nis", rho=rho, cusum=cusum, trigger=False, cusum_k=4.0, cusum_h=20.0
    )
    return x, P, links, params


def test_correct_cusum_discards_persistent_bias():
    """Through the CL step: the gate passes a 2.2-sigma range bias, the CUSUM stops it."""
    filt = make_filter("ekf")
    rho = math.sqrt(chi2_gate(0.01))
    x, P, links, params = _two_robot_links(np.array([[0.0, 0.0]]), rho, True)
    S = filt.relative_moments(x[[0]], P[[0]], x[[1]], P[[1]], params.R).S[0]
    bias = np.array([[2.4 * math.sqrt(S[0, 0]), 0.0]])  # NIS ~ 5.8: under 9.2, above 4
    memory = LinkMemory(2)
    detected = []
    for _ in range(20):
        _, _, links, _ = _two_robot_links(bias, rho, True)
        _, _, out = correct(filt, x, P, links, params, memory)
        detected.append(bool(out.detected[0]))
    assert not detected[0] and detected[-1]
    memory2 = LinkMemory(2)
    params_gate = CLParams(detector_norm="nis", rho=rho, trigger=False)
    for _ in range(20):
        _, _, out = correct(filt, x, P, links, params_gate, memory2)
        assert not out.detected[0]
    with pytest.raises(ValueError, match="LinkMemory"):
        correct(filt, x, P, links, params, None)


# ------------------------------------------------------------------ mean-shift CUSUM


def test_whiten_is_the_cholesky_inverse(rng, random_spd):
    from resloc.cl.cusum import whiten

    S = random_spd(rng, 30, 2, scale=0.01, cond=20)
    nu = rng.normal(size=(30, 2)) * 0.1
    w = whiten(nu, S)
    L = np.linalg.cholesky(S)
    np.testing.assert_allclose(w, np.linalg.solve(L, nu[:, :, None])[:, :, 0], atol=1e-12)
    np.testing.assert_allclose((w * w).sum(1), nis(nu, S), rtol=1e-9)  # |w|^2 = NIS


def test_link_statistic_vectors():
    st = LinkStatistic(10, width=4)
    assert st.get(np.array([1]), np.array([2])).shape == (1, 4)
    st.set(np.array([1, 3]), np.array([2, 2]), np.array([[1.0, 2, 3, 4], [5, 6, 7, 8]]))
    np.testing.assert_array_equal(
        st.get(np.array([3, 1, 0]), np.array([2, 2, 0])),
        [[5, 6, 7, 8], [1, 2, 3, 4], [0, 0, 0, 0]],
    )


def test_mean_cusum_catches_a_signed_bias_the_nis_cusum_cannot(rng):
    """A 1-sigma range bias: mean NIS 3 (never above the NIS CUSUM's k = 3 on average), but
    the signed test on w_r alarms within tens of measurements; honest links stay quiet."""
    from resloc.cl.cusum import link_mean_cusum

    i, j = np.array([0]), np.array([1])
    store, store_nis = LinkStatistic(4, width=4), LinkStatistic(4)
    first = None
    for t in range(400):
        w = rng.normal(size=(1, 2)) + np.array([[1.0, 0.0]])
        link_cusum(store_nis, i, j, (w * w).sum(1), 3.0, 20.0)
        discard = link_mean_cusum(store, i, j, w, 0.5, 8.0)[0]
        g = store.get(i, j)[0]
        if first is None and g[0] > 8.0:
            first = t
        # While a component alarms (either sign), measurements beyond k on either side go.
        expect = ((g[:2] > 8.0).any() and abs(w[0, 0]) > 0.5) or (
            (g[2:] > 8.0).any() and abs(w[0, 1]) > 0.5
        )
        assert discard == expect
    assert first is not None and first < 60
    assert store.get(i, j)[0, 1] < 8.0  # the other side stays quiet
    honest, st2 = 0, LinkStatistic(4, width=4)
    for _ in range(3000):
        honest += int(link_mean_cusum(st2, i, j, rng.normal(size=(1, 2)), 0.5, 8.0)[0])
    assert honest <= 5


def test_correct_mean_cusum_discards_a_one_sigma_bias():
    filt = make_filter("ekf")
    rho = math.sqrt(chi2_gate(0.01))
    x, P, links, _ = _two_robot_links(np.array([[0.0, 0.0]]), rho, False)
    S = filt.relative_moments(x[[0]], P[[0]], x[[1]], P[[1]], CLParams().R).S[0]
    bias = np.array([[1.2 * math.sqrt(S[0, 0]), 0.0]])  # NIS ~ 1.4: under k = 3 of the NIS test
    params = CLParams(detector_norm="nis", rho=rho, trigger=False, cusum=True, mean_cusum=True)
    memory = LinkMemory(2)
    detected = []
    for _ in range(40):
        _, _, links, _ = _two_robot_links(bias, rho, False)
        _, _, out = correct(filt, x, P, links, params, memory)
        detected.append(bool(out.detected[0]))
    assert not detected[0] and detected[-1]
    nis_only = CLParams(detector_norm="nis", rho=rho, trigger=False, cusum=True)
    memory2 = LinkMemory(2)
    for _ in range(40):
        _, _, out = correct(filt, x, P, links, nis_only, memory2)
        assert not out.detected[0]


def test_mean_cusum_ignores_what_the_gate_rejected():
    from resloc.cl.cusum import link_mean_cusum

    i, j = np.array([0, 1]), np.array([1, 0])
    store = LinkStatistic(4, width=4)
    w = np.array([[50.0, 0.0], [50.0, 0.0]])  # gross outliers
    link_mean_cusum(store, i, j, w, 0.5, 8.0, passed=np.array([False, True]))
    np.testing.assert_array_equal(store.get(i[:1], j[:1]), [[0, 0, 0, 0]])
    assert store.get(i[1:], j[1:])[0, 0] == 16.0  # capped at 2h
