"""The compiled claims (:mod:`resloc.cl.kernels_claims`): the redundancy cap and the zone
landmarks' weakened claims in one pass, equal to the numpy stages (the cap's
``capped_claims`` then ``landmark_claims``), and the compiled correction runs it."""

from __future__ import annotations

import numpy as np
import pytest

import resloc.cl.step
from lockstep_helpers import default_world
from resloc.cl import kernels
from resloc.cl.detection_landmark import landmark_claims
from resloc.cl.detection_redundancy_fixes import capped_claims
from resloc.cl.detection_zone import inside_zone_map, zone_map
from resloc.cl.links import LinkBatch, NeighbourStates
from resloc.cl.params import CLParams
from resloc.filters.base import make_filter

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _scene():
    """The default scenario's first step (one trial) at the initial estimates ``x, P``:
    its links with a few claims made tiny or large, and a map around two of the
    neighbours (by their broadcast positions)."""
    world = default_world(1, 4)
    x, P = world.initial_estimates()
    ws = world.step()
    P_nb = P[ws.j].copy()
    P_nb[::4] *= np.linspace(0.01, 5.0, len(P_nb[::4]))[:, None, None]
    links = LinkBatch(
        ws.i, ws.j, ws.z, x[ws.j], P_nb, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
    )
    centres = np.unique(links.x_nb[:, :2], axis=0)[[1, 5]]
    return links, zone_map([((float(cx), float(cy)), 0.05) for cx, cy in centres]), x, P


@pytest.mark.parametrize("cap", [False, True])
def test_the_claims_are_the_numpy_stages(cap: bool) -> None:
    from resloc.cl.kernels_claims import CLAIMS_UNCHANGED, claimed_covariances

    links, discs, _, _ = _scene()
    params = CLParams(
        zone_landmarks=True,
        zone_landmarks_map=discs,
        zone_landmarks_inflation=7.0,
        redundancy=True,
        redundancy_cap_fusion=cap,
    )
    li = links.i.astype(np.int64)
    E = len(li)
    expected = capped_claims(links.P_nb, links.i) if cap else links.P_nb
    expected = landmark_claims(params, links.x_nb, expected, links.i)
    rows = np.arange(E, dtype=np.int64)
    out = np.empty((E, 3, 3))
    scratch = np.empty(E), np.empty(E)
    disc_array = np.asarray(discs, float)
    x_nb = np.ascontiguousarray(links.x_nb)
    inside = claimed_covariances(li, x_nb, links.P_nb, rows, cap, disc_array, 7.0, out, *scratch)
    assert inside >= 2
    np.testing.assert_array_equal(out, expected)
    assert not np.array_equal(out, links.P_nb)
    # nothing inside and no cap: nothing written; the cap alone: the capped claims
    far = disc_array + np.array([1e3, 0.0, 0.0])
    got = claimed_covariances(li, x_nb, links.P_nb, rows, cap, far, 7.0, out, *scratch)
    if cap:
        assert got == 0
        np.testing.assert_array_equal(out, capped_claims(links.P_nb, links.i))
    else:
        assert got == CLAIMS_UNCHANGED


@pytest.mark.parametrize("cap", [False, True])
def test_tiny_claims_inside_the_map_are_raised_to_the_median(cap: bool) -> None:
    """The neighbours inside the map claim far less than their observers' median: the
    pass raises them to the median of the (capped) claims' traces before the inflation,
    as ``landmark_claims`` does, the rows read by index (each source's place tested
    once)."""
    from resloc.cl.kernels_claims import claimed_covariances

    links, discs, _, _ = _scene()
    disc_array = np.asarray(discs, float)
    x_nb = np.ascontiguousarray(links.x_nb)
    inside = inside_zone_map(x_nb[:, :2], discs)
    P_nb = links.P_nb.copy()
    P_nb[inside] *= 1e-3
    P_nb[inside, 0, 0] *= 0.5  # (the position block's trace: not its first entry alone,
    P_nb[inside, 2, 2] *= 50.0  # nor the heading's)
    params = CLParams(
        zone_landmarks=True,
        zone_landmarks_map=discs,
        zone_landmarks_inflation=3.0,
        redundancy=True,
        redundancy_cap_fusion=cap,
    )
    li = links.i.astype(np.int64)
    E = len(li)
    # per row, then by index (the simulator's form: each neighbour's estimate once,
    # its place in the map tested once for all the rows that read it)
    _, first, by_source = np.unique(links.j, return_index=True, return_inverse=True)
    for rows, x_src, P_src in (
        (np.arange(E, dtype=np.int64), x_nb, P_nb),
        (by_source.astype(np.int64), x_nb[first], P_nb[first]),
    ):
        claims = capped_claims(P_src[rows], links.i) if cap else P_src[rows]
        expected = landmark_claims(params, x_src[rows], claims, links.i)
        # raised to the median: by the landmarks' own step, or already by the cap
        before = P_src[rows][inside] if cap else 3.0 * claims[inside]
        after = claims[inside] if cap else expected[inside]
        assert (after[:, 0, 0] + after[:, 1, 1] > 1.01 * (before[:, 0, 0] + before[:, 1, 1])).all()
        out = np.empty((E, 3, 3))
        got = claimed_covariances(
            li, x_src, P_src, rows, cap, disc_array, 3.0, out, np.empty(E), np.empty(E)
        )
        assert got == inside.sum()
        np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("cap", [False, True])
def test_the_compiled_correction_runs_the_claims_pass(cap: bool) -> None:
    """The compiled correction weakens the claims by the compiled pass (counted) and
    equals the reference to 1e-9 with the same decisions."""
    from resloc.cl.kernels_claims import CLAIMS_RUNS

    links, discs, x, P = _scene()
    params = CLParams(
        detector_norm="nis",
        zone_landmarks=True,
        zone_landmarks_map=discs,
        redundancy=cap,
        redundancy_cap_fusion=cap,
    )
    filt = make_filter("ckf")
    before = CLAIMS_RUNS["compiled"]
    with kernels.use_backend("numba"):
        fast = resloc.cl.step.correct(filt, x, P, links, params)
    assert CLAIMS_RUNS["compiled"] == before + 1
    with kernels.use_backend("numpy"):
        ref = resloc.cl.step.correct(filt, x, P, links, params)
    assert fast[2].compiled and not ref[2].compiled
    np.testing.assert_allclose(fast[0], ref[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast[1], ref[1], rtol=0, atol=1e-9)
    for name in ("detected", "triggered", "delivered", "fused"):
        np.testing.assert_array_equal(getattr(fast[2], name), getattr(ref[2], name))


def test_the_claimed_batch_shares_every_other_field() -> None:
    """``claimed_links`` gives a new batch whose claims are the pass's, whose estimates
    are the original's values (gathered by the pass) and whose every other field is the
    original's (a shallow copy, as ``dataclasses.replace``), the original untouched."""
    from resloc.cl.kernels_claims import claimed_links

    links, _, _, _ = _scene()
    before = dict(links.__dict__)
    P_nb = links.P_nb.copy()
    params = CLParams(redundancy=True, redundancy_cap_fusion=True)
    claimed = claimed_links(params, links)
    assert type(claimed) is LinkBatch and claimed is not links
    np.testing.assert_array_equal(claimed.P_nb, capped_claims(P_nb, links.i))
    assert links.__dict__.keys() == before.keys()
    assert all(links.__dict__[k] is v for k, v in before.items())  # the original untouched
    np.testing.assert_array_equal(links.P_nb, P_nb)
    shared = [k for k in before if k not in ("_P_nb", "_x_nb")]
    assert all(claimed.__dict__[k] is before[k] for k in shared), shared
    assert claimed.__dict__.keys() == before.keys()
    assert len(claimed) == len(links)
    np.testing.assert_array_equal(claimed.x_nb, links.x_nb)  # (gathered by the pass)


def test_the_claimed_batch_carries_its_rows_estimates() -> None:
    """A batch that reads its neighbours' estimates by index (``LinkBatch.neighbours``):
    the claimed batch carries the per-row claims and, gathered by the compiled pass, the
    per-row estimates, so that reading them gathers nothing
    (``LinkBatch.neighbour_rows``)."""
    from resloc.cl.kernels_claims import claimed_links

    links, discs, x, P = _scene()
    rng = np.random.default_rng(3)
    source_x = x + rng.normal(0.0, 0.1, x.shape)
    source_P = P * rng.uniform(0.2, 3.0, len(P))[:, None, None]
    by_index = LinkBatch(
        links.i, links.j, links.z, None, None, links.channel_ok, links.risk_s, links.risk_c,
        links.lambda2, neighbours=NeighbourStates(links.j, source_x, source_P),
    )  # fmt: skip
    params = CLParams(
        zone_landmarks=True, zone_landmarks_map=discs, redundancy=True, redundancy_cap_fusion=True
    )
    claimed = claimed_links(params, by_index)
    carried = claimed.__dict__.get("_x_nb")
    assert carried is not None  # (not gathered on read)
    index, x_rows, P_rows = claimed.neighbour_rows()
    assert index is None and x_rows is carried
    np.testing.assert_array_equal(x_rows, source_x[links.j])
    expected = landmark_claims(
        params, source_x[links.j], capped_claims(source_P[links.j], links.i), links.i
    )
    np.testing.assert_array_equal(P_rows, expected)
    assert by_index.__dict__.get("_x_nb") is None  # the original gathered nothing


def test_the_capped_claims_median_from_the_first_order_is_a_full_sorts() -> None:
    """With the cap and the map, the median of the capped claims is read from the order of
    the claims before the cap merged with the raised rows' new traces
    (``raised_trace_scales``): the same factors as sorting the capped traces
    (``trace_scales``) and the numpy stages' claims, on groups of tied traces, zero and
    negative traces, traces just above and below the median, and a NaN (then sorted)."""
    from resloc.cl.kernels_claims import claimed_covariances, raised_trace_scales
    from resloc.cl.kernels_redundancy_fixes import claim_scales, trace_scales

    rng = np.random.default_rng(12)
    checked = 0
    for trial in range(300):
        sizes = rng.integers(1, 18, rng.integers(1, 9))
        li = np.repeat(np.arange(len(sizes)), sizes).astype(np.int64)
        E = len(li)
        # few distinct values per trial: ties inside and across the raised run
        levels = rng.choice([0.0, -0.5, 1e-3, 0.2, 0.2, 1.0, 1.0 + 1e-15, 3.0, 7.5], 6)
        P = np.zeros((E, 3, 3))
        P[:, 0, 0] = rng.choice(levels, E) * rng.choice([1.0, 1.0, 1.0 / 3.0], E)
        P[:, 1, 1] = rng.choice(levels, E)
        P[:, 2, 2] = 1.0
        if trial % 50 == 7:
            P[rng.integers(E), 1, 1] = np.nan
        rows = np.arange(E, dtype=np.int64)
        scale, ranked = np.empty(E), np.empty(E)
        claim_scales(li, P, rows, scale, ranked)
        capped = P * scale[:, None, None]
        traces = capped[:, 0, 0] + capped[:, 1, 1]
        expected = traces.copy()
        trace_scales(li, expected, np.empty(E))
        got = traces.copy()
        if raised_trace_scales(li, got, scale != 1.0, ranked, np.empty(E)):
            np.testing.assert_array_equal(got, expected)
            checked += 1
        else:
            assert np.isnan(traces).any()
            np.testing.assert_array_equal(got, traces)  # nothing written
            continue
        # the whole pass, every neighbour inside the map: the numpy stages' claims
        x_src = np.zeros((E, 3))
        params = CLParams(
            zone_landmarks=True,
            zone_landmarks_map=((0.0, 0.0, 1.0),),
            zone_landmarks_inflation=2.0,
            redundancy=True,
            redundancy_cap_fusion=True,
        )
        want = landmark_claims(params, x_src, capped_claims(P, li), li)
        out = np.empty((E, 3, 3))
        discs = np.array([[0.0, 0.0, 1.0]])
        claimed_covariances(li, x_src, P, rows, True, discs, 2.0, out, np.empty(E), np.empty(E))
        np.testing.assert_array_equal(out, want)
    assert checked > 250


def test_claims_of_other_shapes_are_refused_by_the_pass() -> None:
    """``claimed_rows`` refuses (``CLAIMS_UNSORTED``: the caller then takes the numpy
    stage's way, or the reference's) estimates of fewer than two components, claims that
    are not 3 x 3 and rows that are not one per link, writing nothing; ``claimed_links``
    then gives the numpy stage's batch (landmarks alone) or None (with the cap)."""
    from resloc.cl.kernels_claims import CLAIMS_UNSORTED, claimed_links, claimed_rows

    links, discs, _, _ = _scene()
    li = links.i.astype(np.int64)
    E = len(li)
    rows = np.arange(E, dtype=np.int64)
    x_nb = np.ascontiguousarray(links.x_nb)
    P_nb = np.ascontiguousarray(links.P_nb)
    disc_array = np.asarray(discs, float)
    for x_src, P_src, at in (
        (x_nb[:, :1].copy(), P_nb, rows),
        (x_nb, P_nb[:, :2, :2].copy(), rows),
        (x_nb, P_nb, rows[:-1].copy()),
    ):
        inside, out, x_out = claimed_rows(li, x_src, P_src, at, True, disc_array, 3.0)
        assert inside == CLAIMS_UNSORTED and out.shape == (0, 3, 3) and x_out.shape == (0, 3)
    inside, out, _ = claimed_rows(li, x_nb, P_nb, rows, True, disc_array, 3.0)
    assert inside > 0 and out.shape == (E, 3, 3)
    flat = LinkBatch(
        links.i, links.j, links.z, x_nb[:, :1].copy(), P_nb, links.channel_ok, links.risk_s,
        links.risk_c, links.lambda2,
    )  # fmt: skip
    capped = CLParams(redundancy=True, redundancy_cap_fusion=True)
    assert claimed_links(capped, flat) is None
