"""The vectorized engine (issue 4): the compiled CL correction against the numpy reference
path, backend selection and fallbacks, and the scalable ``lambda2``."""

from __future__ import annotations

import enum
from dataclasses import fields, replace

import numpy as np
import pytest
import scipy.sparse as sp

from lockstep_helpers import default_world, runner_step, start_states
from resloc.angles import wrap_angle
from resloc.cl import (
    CLParams,
    LinkBatch,
    LinkMemory,
    ThresholdInnovation,
    UpdateMode,
    correct,
    kernels,
    kernels_math,
)
from resloc.cl.backend import kernel_refusal
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.graph import DENSE_MAX, Lambda2Memo, algebraic_connectivity, component_lambda2
from resloc.cl.graph import laplacian as graph_laplacian
from resloc.errors import ConfigError, NumericalError
from resloc.experiments.config import default_scenario
from resloc.filters import SigmaPointFilter, covariance_is_pd, make_filter, repair_covariance
from resloc.filters.base import FilterKind
from resloc.filters.sigma_points import cubature_rule
from resloc.models import range_bearing
from resloc.world.network import radius_links

needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")
FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
    "ckf-arith": SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), False),
}
FIELDS = ("norm", "threshold", "detected", "triggered", "delivered", "fused", "repaired", "repairs")


def random_batch(seed: int, B: int = 40, outliers: float = 0.1, fail: float = 0.2):
    """``B`` robots, each observing 0..6 others (sorted by i then j), some measurements
    falsified, some channels failing, random risks and connectivity (some zero)."""
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(0, 5, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    sd = rng.uniform(0.01, 0.2, B)
    x = truth + sd[:, None] * rng.normal(size=(B, 3))
    x[:, 2] = wrap_angle(x[:, 2])
    A = rng.normal(size=(B, 3, 3)) * sd[:, None, None]
    P = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(3)
    ii, jj = [], []
    for i in range(B):
        nb = np.sort(rng.choice(np.setdiff1d(np.arange(B), [i]), rng.integers(0, 7), False))
        ii += [i] * len(nb)
        jj += list(nb)
    i, j = np.array(ii, dtype=np.int64), np.array(jj, dtype=np.int64)
    z = range_bearing(truth[i], truth[j]) + rng.normal(size=(len(i), 2)) * [0.02, 0.03]
    bad = rng.random(len(i)) < outliers
    z[bad] += rng.normal(size=(int(bad.sum()), 2)) * [2.0, 1.0]
    z[:, 0] = np.abs(z[:, 0])
    z[:, 1] = wrap_angle(z[:, 1])
    lambda2 = rng.uniform(0.2, 3.0, B)
    lambda2[rng.random(B) < 0.1] = 0.0
    links = LinkBatch(
        i, j, z, x[j].copy(), P[j].copy(), rng.random(len(i)) >= fail,
        rng.uniform(0, 0.7, B), rng.uniform(0, 0.7, B), lambda2,
    )  # fmt: skip
    return x, P, links


def run_both(filt, x, P, links, params, memories=(None, None)):
    """The correction by the compiled kernel and by the numpy reference; asserts which path
    computed each."""
    out = {}
    for backend, memory in zip(("numba", "numpy"), memories, strict=True):
        with kernels.use_backend(backend):
            out[backend] = correct(filt, x, P, links, params, memory)
    assert out["numba"][2].compiled, "the compiled kernel did not run"
    assert not out["numpy"][2].compiled
    return out["numba"], out["numpy"]


def assert_equivalent(fast, ref, tol: float = 1e-9) -> None:
    """The compiled kernel's correction ``fast`` equals the reference path's ``ref``; asserts
    that each came from its path."""
    (xf, Pf, of), (xr, Pr, orf) = fast, ref
    assert of.compiled and not orf.compiled, "compared the wrong paths"
    d = xf - xr
    d[:, 2] = wrap_angle(d[:, 2])
    assert np.abs(d).max() <= tol
    assert np.abs(Pf - Pr).max() <= tol
    for name in FIELDS:
        a, b = getattr(of, name), getattr(orf, name)
        if name in ("norm", "threshold"):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, equal_nan=True)
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)


PARAM_CASES = {
    "paper": CLParams(range_std=0.02, bearing_std=0.03, rho=1.0, alpha=0.05),
    "scaled-norms": CLParams(
        range_std=0.02, bearing_std=0.03, rho=20.0, alpha=0.3,
        detector_norm="scaled", trigger_norm="scaled",
    ),
    "nis-mixed": CLParams(
        range_std=0.02, bearing_std=0.03, rho=25.0, alpha=0.02,
        detector_norm="nis", trigger_norm="euclidean",
    ),
    "detector-off": CLParams(range_std=0.02, bearing_std=0.03, detector=False, alpha=0.05),
    "trigger-off": CLParams(range_std=0.02, bearing_std=0.03, rho=1.0, trigger=False),
    "risk-floor": CLParams(
        range_std=0.02, bearing_std=0.03, rho=1.0, alpha=0.5, zeta_s=2.0, risk_factor_floor=0.1,
    ),
}  # fmt: skip


@needs_numba
@pytest.mark.parametrize("case", list(PARAM_CASES))
@pytest.mark.parametrize("name", list(FILTERS))
def test_kernel_matches_reference(name: str, case: str) -> None:
    x, P, links = random_batch(11)
    fast, ref = run_both(FILTERS[name], x, P, links, PARAM_CASES[case])
    assert_equivalent(fast, ref)
    out = ref[2]
    assert out.fused.any() and not out.fused.all()


@needs_numba
@pytest.mark.parametrize("name", ["ckf", "ukf", "ekf"])
def test_kernel_matches_reference_with_per_robot_gains(name: str) -> None:
    x, P, links = random_batch(12)
    rng = np.random.default_rng(0)
    B = len(x)
    params = CLParams(
        range_std=0.02, bearing_std=0.03, rho=rng.uniform(0.3, 2.0, B),
        alpha=rng.uniform(0.0, 0.2, B), gamma=rng.uniform(0, 2, B),
        zeta_s=rng.uniform(0, 1, B), zeta_c=rng.uniform(0, 1, B),
    )  # fmt: skip
    assert_equivalent(*run_both(FILTERS[name], x, P, links, params))


@needs_numba
@pytest.mark.parametrize("name", ["ckf", "ekf"])
def test_kernel_last_sent_threshold_keeps_the_same_memory(name: str) -> None:
    params = CLParams(
        range_std=0.02, bearing_std=0.03, rho=1.0, alpha=0.05,
        threshold_innovation=ThresholdInnovation.LAST_SENT,
    )  # fmt: skip
    mem_fast, mem_ref = LinkMemory(40), LinkMemory(40)
    for seed in (3, 4, 5):  # later calls read what earlier ones stored
        x, P, links = random_batch(seed)
        fast, ref = run_both(FILTERS[name], x, P, links, params, (mem_fast, mem_ref))
        assert_equivalent(fast, ref)
    assert len(mem_ref) > 0
    np.testing.assert_array_equal(mem_fast.keys, mem_ref.keys)
    np.testing.assert_array_equal(mem_fast.x, mem_ref.x)
    np.testing.assert_array_equal(mem_fast.P, mem_ref.P)
    np.testing.assert_allclose(mem_fast.last_norm, mem_ref.last_norm, rtol=1e-12)


def lockstep_both_backends(world, filt, params, steps: int):
    """``steps`` world steps through the compiled and the reference CL step side by side,
    each path carrying its own estimates and link memory; after each step checks that the
    two agree (and which path ran), then yields ``(results, memories)`` keyed by backend."""
    fusion = fusion_strategy(params.fusion)  # its bookkeeping runs as in the runner
    state = start_states(world, ("numba", "numpy"), fusion)
    for _ in range(steps):
        ws = world.step()
        res = {}
        for backend, (x, P, memory) in state.items():
            with kernels.use_backend(backend):
                res[backend] = runner_step(filt, x, P, ws, world.dt, params, fusion, memory)
            state[backend] = (res[backend][0], res[backend][1], memory)
        assert_equivalent(res["numba"], res["numpy"])
        yield res, {backend: s[2] for backend, s in state.items()}


@needs_numba
@pytest.mark.parametrize("name", ["ckf", "ukf", "ekf"])
def test_engine_matches_reference_over_a_scenario(name: str) -> None:
    """The default scenario (two trials batched) for 150 steps: same estimates to 1e-9 and
    identical detector/trigger/channel decisions at every step."""
    world = default_world(2, 1)
    params = default_scenario().cl_params()
    filt = FILTERS[name]
    for _ in lockstep_both_backends(world, filt, params, 150):
        pass  # each step is compared inside


@needs_numba
def test_kernel_counts_and_repairs_non_pd_covariances() -> None:
    """The kernel's PD check and eigenvalue repair are the reference's."""
    rng = np.random.default_rng(2)
    A = rng.normal(size=(200, 3, 3))
    P = A @ np.swapaxes(A, 1, 2)
    w, V = np.linalg.eigh(P)
    w[:, 0] = rng.uniform(-1e-3, 1e-3, 200)  # about half indefinite
    P = np.einsum("bij,bj,bkj->bik", V, w, V)
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    ok = covariance_is_pd(P)
    assert 0 < ok.sum() < len(P)
    assert [kernels_math.is_pd3(p) for p in P] == list(ok)
    bad = P[~ok]
    fixed = bad.copy()
    for p in fixed:
        kernels_math.repair3(p)
    np.testing.assert_allclose(fixed, repair_covariance(bad), rtol=0, atol=1e-12)
    assert covariance_is_pd(fixed).all()


@needs_numba
def test_kernel_raises_like_the_reference_on_a_nan_covariance() -> None:
    x, P, links = random_batch(6)
    P[links.i[0]] = np.nan
    for backend in ("numba", "numpy"):
        with kernels.use_backend(backend), pytest.raises(NumericalError):
            correct(FILTERS["ckf"], x, P, links, PARAM_CASES["paper"])


@needs_numba
def test_inconsistent_shapes_go_to_the_reference_which_raises() -> None:
    """The compiled loop does not bounds-check: bad input never reaches it."""
    x, P, links = random_batch(8)
    short = replace(links, lambda2=links.lambda2[:3])
    params = PARAM_CASES["paper"]
    with kernels.use_backend("numba"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, short, params) is None
        with pytest.raises(IndexError):
            correct(FILTERS["ckf"], x, P, short, params)
        few_gains = replace(params, rho=np.ones(3))
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, few_gains) is None


@needs_numba
def test_uncovered_options_fall_back_to_the_reference() -> None:
    x, P, links = random_batch(7)
    base = PARAM_CASES["paper"]
    with kernels.use_backend("numba"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, base) is not None
        # the summed update with a fusion method its twin lacks (kernels_summed: naive only)
        summed = replace(base, update_mode=UpdateMode.SUMMED, fusion="ci")
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, summed, LinkMemory(40)) is None

        # A filter class the kernel does not know.
        class Custom(SigmaPointFilter):
            pass

        custom = Custom(FilterKind.CKF, cubature_rule(3), cubature_rule(6))
        assert kernels.fast_correct(custom, x, P, links, base) is None
        # A duplicated link.
        dup = LinkBatch(
            links.i[[0, 0]], links.j[[0, 0]], links.z[[0, 0]], links.x_nb[[0, 0]],
            links.P_nb[[0, 0]], links.channel_ok[[0, 0]], links.risk_s, links.risk_c,
            links.lambda2,
        )  # fmt: skip
        assert kernels.fast_correct(FILTERS["ckf"], x, P, dup, base) is None
    with kernels.use_backend("numpy"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, base) is None


def _other_values(value):
    """Non-default values of a CLParams field, whatever its type (also for fields added later)."""
    from resloc.cl.fusion import FusionMethod  # the registered fusion methods' names

    if isinstance(value, enum.Enum | FusionMethod):
        return [v for v in type(value) if v is not value]
    if isinstance(value, bool):
        return [not value]
    if value is None:
        return [10.0]
    if isinstance(value, tuple):
        return [tuple(1.5 * v + 0.01 for v in value)]
    return [1.5 * value + 0.05]


@needs_numba
@pytest.mark.parametrize("name", [f.name for f in fields(CLParams)])
def test_kernel_coverage_is_honest_for_every_option(name: str) -> None:
    """Every CLParams option, set away from its default: either the kernel refuses it (and
    says why), or the kernel runs and equals the reference. A field the kernel ignored would
    fail here."""
    x, P, links = random_batch(5)
    base = PARAM_CASES["paper"]
    for value in _other_values(getattr(base, name)):
        params = replace(base, **{name: value})
        with kernels.use_backend("numba"):
            refusal = kernel_refusal(FILTERS["ckf"], params, links)
            if refusal is not None:
                assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params) is None
                continue
        memories = (LinkMemory(40), LinkMemory(40))
        for memory in memories:  # a fusion method's own state, as a run sets it up
            fusion_strategy(params.fusion).init(memory, x, P, len(x))
        assert_equivalent(*run_both(FILTERS["ckf"], x, P, links, params, memories))


def test_backend_switch_validates_and_restores() -> None:
    before = kernels.backend()
    with pytest.raises(ConfigError, match="backend must be one of"):
        kernels.set_backend("fortran")
    with kernels.use_backend("numpy"):
        assert kernels.backend() == "numpy"
        assert kernels.warm_up() is False
    assert kernels.backend() == before
    assert kernels.backend() == ("numba" if kernels.HAVE_NUMBA else "numpy")


@needs_numba
def test_wrap_kernel_is_bitwise_numpy() -> None:
    a = np.concatenate(
        [np.linspace(-20, 20, 2001), [np.pi, -np.pi, 0.0, -0.0, 3 * np.pi, 1e-300, 7e5]]
    )
    np.testing.assert_array_equal([kernels_math.wrap(v) for v in a], wrap_angle(a))


# --------------------------------------------------------------------------------------
# lambda2 at scale
# --------------------------------------------------------------------------------------
def geometric(n: int, degree: float, seed: int, teams: int = 1):
    rng = np.random.default_rng(seed)
    side = np.sqrt(n * np.pi / degree)  # unit radius: mean degree ~ `degree`
    p = rng.uniform(0, side, (n, 2))
    team = np.repeat(np.arange(teams), n // teams)
    return radius_links(p, team, 1.0)


def test_sparse_lambda2_matches_dense() -> None:
    for n, seed in ((400, 1), (700, 2)):
        i, j = geometric(n, 14.0, seed)
        L = graph_laplacian(i, j, n)
        dense = algebraic_connectivity(L.toarray())
        sparse = algebraic_connectivity(L)
        assert n > DENSE_MAX
        if dense == 0.0:
            assert sparse == 0.0
        else:
            assert sparse == pytest.approx(dense, rel=1e-9)
    # Disconnected large graph: exactly 0, as the dense tolerance gives.
    L2 = sp.block_diag([L, L]).tocsr()
    assert algebraic_connectivity(L2) == 0.0


def test_batched_small_components_equal_the_per_component_solve() -> None:
    """Many small components of mixed sizes: one batched dense eigensolve per size gives
    bit for bit the per-component value."""
    n = 3000
    i, j = geometric(n, 3.0, 4)
    out = component_lambda2(i, j, n)
    L = graph_laplacian(i, j, n)
    _, labels = sp.csgraph.connected_components(L, directed=False)
    sizes = np.bincount(labels)
    assert len(np.unique(sizes)) > 5
    for c in np.flatnonzero(sizes > 1)[:200]:
        idx = np.flatnonzero(labels == c)
        assert out[idx[0]] == algebraic_connectivity(L[idx][:, idx])
        assert np.all(out[idx] == out[idx[0]])
    assert np.all(out[sizes[labels] == 1] == 0.0)


def test_lambda2_memo_skips_unchanged_large_components() -> None:
    i1, j1 = geometric(600, 14.0, 5)
    i2, j2 = geometric(600, 14.0, 6)
    n = 1200
    i = np.concatenate([i1, i2 + 600])
    j = np.concatenate([j1, j2 + 600])
    memo = Lambda2Memo()
    first = component_lambda2(i, j, n, memo=memo)
    assert memo.solves >= 2 and memo.hits == 0
    # Change the second half only: the first half's components are reused.
    keep = i < 600
    drop = np.flatnonzero(~keep)[:2]
    mask = np.ones(len(i), bool)
    mask[drop] = False
    rev = np.flatnonzero((i == j[drop[0]]) & (j == i[drop[0]]))
    mask[rev] = False
    solves = memo.solves
    second = component_lambda2(i[mask], j[mask], n, memo=memo)
    assert memo.hits >= 1
    np.testing.assert_array_equal(second[:600], first[:600])
    assert memo.solves > solves
    np.testing.assert_array_equal(component_lambda2(i, j, n), first)


def test_global_lambda2_per_group_large_groups() -> None:
    i, j = geometric(800, 14.0, 7, teams=2)
    team = np.repeat([0, 1], 400)
    out = component_lambda2(i, j, 800, mode="global", group=team)
    L = graph_laplacian(i, j, 800).toarray()
    for t in (0, 1):
        idx = np.flatnonzero(team == t)
        expected = algebraic_connectivity(L[np.ix_(idx, idx)])
        np.testing.assert_allclose(out[idx], expected, rtol=1e-9, atol=1e-12)
