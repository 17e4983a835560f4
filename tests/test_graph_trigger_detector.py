"""Tests of ``lambda2`` (:mod:`resloc.cl.graph`), the event trigger (eqs. 10-11) and the
innovation-residual attack detector (:mod:`resloc.cl.detector`)."""

from __future__ import annotations

import warnings

import networkx as nx
import numpy as np
import pytest

from resloc.cl import (
    InnovationNorm,
    algebraic_connectivity,
    attack_detected,
    component_lambda2,
    event_threshold,
    event_triggered,
    innovation_norm,
    laplacian,
)


def edges_of(G: nx.Graph) -> tuple[np.ndarray, np.ndarray]:
    e = np.array(list(G.edges()), dtype=int).reshape(-1, 2)
    return e[:, 0], e[:, 1]


def nx_lambda2(G: nx.Graph) -> float:
    """networkx reference; 0 for a single node (networkx refuses graphs with < 2 nodes)."""
    if G.number_of_nodes() < 2:
        return 0.0
    return float(nx.algebraic_connectivity(G, method="tracemin_lu", tol=1e-12, seed=0))


def geometric_graph(n: int, radius: float, seed: int) -> nx.Graph:
    return nx.random_geometric_graph(n, radius, seed=seed)


# Radii chosen so that some graphs are connected and some are not (checked in the tests).
GRAPHS = [
    (12, 0.5, 1),
    (12, 0.6, 1),
    (16, 0.45, 8),
    (20, 0.4, 2),
    (25, 0.3, 3),
    (30, 0.2, 4),
    (15, 0.25, 5),
    (40, 0.35, 6),
]


# --------------------------------------------------------------------------------------
# Graph
# --------------------------------------------------------------------------------------
def test_laplacian_matches_networkx_and_ignores_duplicates() -> None:
    G = geometric_graph(15, 0.4, 7)
    i, j = edges_of(G)
    L = laplacian(i, j, 15).toarray()
    L_nx = nx.laplacian_matrix(G, nodelist=range(15)).toarray()
    np.testing.assert_array_equal(L, L_nx)
    # Both directions and repeated edges give the same simple graph.
    L2 = laplacian(np.concatenate([i, j, i]), np.concatenate([j, i, j]), 15).toarray()
    np.testing.assert_array_equal(L2, L_nx)


@pytest.mark.parametrize(("n", "radius", "seed"), GRAPHS)
def test_global_lambda2_matches_networkx(n: int, radius: float, seed: int) -> None:
    G = geometric_graph(n, radius, seed)
    i, j = edges_of(G)
    out = component_lambda2(i, j, n, mode="global")
    assert out.shape == (n,)
    expected = nx_lambda2(G) if nx.is_connected(G) else 0.0
    np.testing.assert_allclose(out, expected, atol=1e-8)
    assert algebraic_connectivity(laplacian(i, j, n)) == pytest.approx(expected, abs=1e-8)


@pytest.mark.parametrize(("n", "radius", "seed"), GRAPHS)
def test_component_lambda2_matches_networkx_per_component(n: int, radius: float, seed: int) -> None:
    G = geometric_graph(n, radius, seed)
    i, j = edges_of(G)
    out = component_lambda2(i, j, n, mode="component")
    for comp in nx.connected_components(G):
        nodes = sorted(comp)
        np.testing.assert_allclose(out[nodes], nx_lambda2(G.subgraph(nodes)), atol=1e-8)


def test_graph_set_has_connected_and_disconnected_cases() -> None:
    connected = [nx.is_connected(geometric_graph(*g)) for g in GRAPHS]
    assert any(connected)
    assert not all(connected)
    # ...and a disconnected one with a non-trivial component, so 'component' != 'global'.
    G = geometric_graph(30, 0.2, 4)
    assert not nx.is_connected(G)
    i, j = edges_of(G)
    assert component_lambda2(i, j, 30).max() > 0.0


def test_isolated_nodes_and_empty_graph() -> None:
    i = np.array([0, 1])
    j = np.array([1, 2])  # path 0-1-2, nodes 3 and 4 isolated
    out = component_lambda2(i, j, 5)
    np.testing.assert_allclose(out[:3], 1.0, atol=1e-12)  # lambda2 of a 3-path is 1
    np.testing.assert_array_equal(out[3:], 0.0)
    np.testing.assert_array_equal(component_lambda2(i, j, 5, mode="global"), 0.0)
    empty = np.array([], dtype=int)
    np.testing.assert_array_equal(component_lambda2(empty, empty, 4), 0.0)
    assert algebraic_connectivity(np.zeros((1, 1))) == 0.0


def test_known_lambda2_values() -> None:
    n = 6
    K = nx.complete_graph(n)
    i, j = edges_of(K)
    np.testing.assert_allclose(component_lambda2(i, j, n), n, atol=1e-12)  # K_n: n
    C = nx.cycle_graph(n)
    i, j = edges_of(C)
    np.testing.assert_allclose(
        component_lambda2(i, j, n), 2 - 2 * np.cos(2 * np.pi / n), atol=1e-12
    )  # C_n: 2 - 2 cos(2 pi / n)
    # Dense and sparse inputs agree.
    L = laplacian(i, j, n)
    assert algebraic_connectivity(L) == pytest.approx(algebraic_connectivity(L.toarray()))


def test_group_argument_takes_global_lambda2_per_group() -> None:
    """Independent graphs batched together: 'global' per group; 'component' unaffected."""
    graphs = [geometric_graph(*g) for g in [(20, 0.4, 2), (30, 0.2, 4), (12, 0.6, 1)]]
    assert [nx.is_connected(G) for G in graphs] == [True, False, True]
    offset, ii, jj, group, expected_global, expected_comp = 0, [], [], [], [], []
    for g, G in enumerate(graphs):
        i, j = edges_of(G)
        ii.append(i + offset)
        jj.append(j + offset)
        n = G.number_of_nodes()
        group += [g] * n
        expected_global += [nx_lambda2(G) if nx.is_connected(G) else 0.0] * n
        expected_comp.append(component_lambda2(i, j, n))
        offset += n
    i, j, group = np.concatenate(ii), np.concatenate(jj), np.array(group)
    out = component_lambda2(i, j, offset, mode="global", group=group)
    np.testing.assert_allclose(out, expected_global, atol=1e-8)
    assert out[group == 0].min() > 0.0
    np.testing.assert_array_equal(out[group == 1], 0.0)
    out_c = component_lambda2(i, j, offset, mode="component", group=group)
    np.testing.assert_allclose(out_c, np.concatenate(expected_comp), atol=1e-12)
    # Without groups the batch is one disconnected graph: 0 everywhere.
    np.testing.assert_array_equal(component_lambda2(i, j, offset, mode="global"), 0.0)
    # Group labels need not be contiguous or sorted.
    out2 = component_lambda2(i, j, offset, mode="global", group=np.array([7, 3, 5])[group])
    np.testing.assert_allclose(out2, out, atol=1e-12)


def test_single_node_group_is_zero() -> None:
    group = np.array([0, 0, 1])
    out = component_lambda2(np.array([0]), np.array([1]), 3, mode="global", group=group)
    np.testing.assert_allclose(out, [2.0, 2.0, 0.0], atol=1e-12)


def test_unknown_mode_raises() -> None:
    with pytest.raises(ValueError, match="component"):
        component_lambda2(np.array([0]), np.array([1]), 2, mode="local")


# --------------------------------------------------------------------------------------
# Event trigger, eqs. (10) and (11)
# --------------------------------------------------------------------------------------
def test_event_threshold_hand_computed() -> None:
    # 0.3 / 1.5 * (1 + 0.5 * 0.4) * (1 - 0.5 * 0.2 - 0.5 * 0.4) = 0.2 * 1.2 * 0.7
    d = event_threshold(0.3, np.array([1.5]), 0.5, np.array([0.4]), 0.5, np.array([0.2]), 0.5,
                        np.array([0.4]))  # fmt: skip
    np.testing.assert_allclose(d, [0.168], rtol=1e-14)


def test_event_threshold_vectorized_with_per_link_gains(rng: np.random.Generator) -> None:
    E = 50
    alpha, gamma = rng.uniform(0.1, 1, E), rng.uniform(0, 2, E)
    zs, zc = rng.uniform(0, 0.5, E), rng.uniform(0, 0.5, E)
    lam, size = rng.uniform(0.1, 3, E), rng.uniform(0, 2, E)
    ds, dc = rng.uniform(0, 1, E), rng.uniform(0, 1, E)
    d = event_threshold(alpha, lam, gamma, size, zs, ds, zc, dc)
    for e in range(E):
        risk = max(1.0 - zs[e] * ds[e] - zc[e] * dc[e], 0.0)
        assert d[e] == pytest.approx(alpha[e] / lam[e] * (1 + gamma[e] * size[e]) * risk)


def test_event_threshold_disconnected_is_infinite() -> None:
    lam = np.array([0.0, 0.0, 1e-12, 2.0])
    size = np.array([0.3, 1e6, 0.3, 0.3])
    d = event_threshold(0.3, lam, 0.5, size, 0.5, np.full(4, 0.2), 0.5, np.full(4, 0.2))
    assert np.isinf(d[:2]).all()
    assert np.isfinite(d[2:]).all()
    assert d[2] > 1e10
    assert not event_triggered(size, d)[:2].any()


def test_risk_factor_clipped_to_floor() -> None:
    """``1 - zeta_s Ds - zeta_c Dc <= 0`` is clipped to the floor; with floor 0 the threshold
    is 0 and every strictly positive innovation triggers."""
    ds = np.array([1.0, 1.0, 0.9, 0.2])
    dc = np.array([1.0, 0.5, 1.0, 0.2])  # risk factors -0.5, 0.0, -0.3 (zeta = 0.75), 0.7
    lam = np.ones(4)
    d = event_threshold(0.3, lam, 0.5, np.full(4, 0.4), 0.75, ds, 0.75, dc)
    np.testing.assert_allclose(d, [0.0, 0.0, 0.0, 0.3 * 1.2 * 0.7], rtol=1e-14)
    np.testing.assert_array_equal(
        event_triggered(np.array([1e-12, 0.0, 5.0, 0.2]), d), [True, False, True, False]
    )
    d_floor = event_threshold(0.3, lam, 0.5, np.full(4, 0.4), 0.75, ds, 0.75, dc, 0.1)
    np.testing.assert_allclose(d_floor, [0.036, 0.036, 0.036, 0.252], rtol=1e-14)
    # Disconnected and risk factor 0 (inf * 0): no transmission, not NaN, and no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d0 = event_threshold(0.3, np.zeros(1), 0.5, np.ones(1), 1.0, np.ones(1), 1.0, np.ones(1))
    assert np.isinf(d0[0])


def test_event_triggered_is_strict() -> None:
    size = np.array([0.5, 0.5, 0.49, np.inf])
    delta = np.array([0.5, 0.49, 0.5, np.inf])
    np.testing.assert_array_equal(event_triggered(size, delta), [False, True, False, False])


# --------------------------------------------------------------------------------------
# Innovation norms and the detector
# --------------------------------------------------------------------------------------
def test_innovation_norms_hand_computed() -> None:
    nu = np.array([[0.3, 0.4], [-0.1, 0.0], [0.0, -0.2]])
    S = np.array([[[0.04, 0.0], [0.0, 0.01]], [[1.0, 0.5], [0.5, 1.0]], [[2.0, 0.0], [0.0, 4.0]]])
    std = np.array([0.1, 0.05])
    np.testing.assert_allclose(
        innovation_norm(nu, S, InnovationNorm.EUCLIDEAN, std), [0.5, 0.1, 0.2], rtol=1e-14
    )
    np.testing.assert_allclose(
        innovation_norm(nu, S, InnovationNorm.SCALED, std),
        [np.hypot(3.0, 8.0), 1.0, 4.0],
        rtol=1e-14,
    )
    # nis: sqrt(0.09/0.04 + 0.16/0.01) ; 0.01 * (S^-1)_00 = 0.01 * 4/3 ; 0.04 / 4
    np.testing.assert_allclose(
        innovation_norm(nu, S, InnovationNorm.NIS, std),
        [np.sqrt(2.25 + 16.0), np.sqrt(0.01 * 4.0 / 3.0), 0.1],
        rtol=1e-12,
    )


def test_nis_matches_numpy_solve(rng: np.random.Generator, random_spd) -> None:
    nu = rng.normal(size=(40, 2))
    S = random_spd(rng, 40, 2, scale=0.5, cond=100.0)
    expected = np.sqrt(np.einsum("ei,ei->e", nu, np.linalg.solve(S, nu[:, :, None])[:, :, 0]))
    np.testing.assert_allclose(innovation_norm(nu, S, "nis", np.ones(2)), expected, rtol=1e-10)


def test_innovation_norm_accepts_strings() -> None:
    nu = np.array([[0.3, 0.4]])
    S = np.eye(2)[None] * 4.0
    assert innovation_norm(nu, S, "euclidean", np.ones(2))[0] == pytest.approx(0.5)
    assert innovation_norm(nu, S, "scaled", np.array([0.1, 0.1]))[0] == pytest.approx(5.0)
    assert innovation_norm(nu, S, "nis", np.ones(2))[0] == pytest.approx(0.25)
    with pytest.raises(ValueError):
        innovation_norm(nu, S, "manhattan", np.ones(2))


def test_attack_detected() -> None:
    norm = np.array([0.1, 0.5, 0.50001, 10.0])
    np.testing.assert_array_equal(attack_detected(norm, 0.5), [False, False, True, True])
    np.testing.assert_array_equal(attack_detected(norm, np.inf), False)
    rho = np.array([0.05, 1.0, 1.0, 20.0])
    np.testing.assert_array_equal(attack_detected(norm, rho), [True, False, False, False])
