"""What makes a step of a million robots affordable: neighbour estimates read by index
(``LinkBatch.from_predicted``), cell-list neighbour search, robots kept in square order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from resloc.cl import CLParams, LinkBatch, LinkMemory, ThresholdInnovation, correct, kernels
from resloc.cl.links import NeighbourStates
from resloc.filters import make_filter
from resloc.world.network import radius_links

needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def swarm_links(seed: int, B: int = 60):
    """A random swarm and its links in both forms: copies and by index."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(B / 1.9)
    truth = np.column_stack([rng.uniform(0, side, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    x = truth + 0.05 * rng.normal(size=(B, 3))
    A = 0.05 * rng.normal(size=(B, 3, 3))
    P = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(3)
    i, j = radius_links(truth[:, :2], np.zeros(B, np.int64), 1.0)
    dx = truth[j, :2] - truth[i, :2]
    z = np.column_stack(
        [np.hypot(dx[:, 0], dx[:, 1]), np.arctan2(dx[:, 1], dx[:, 0]) - truth[i, 2]]
    ) + 0.01 * rng.normal(size=(len(i), 2))
    z[:, 1] = (z[:, 1] + np.pi) % (2 * np.pi) - np.pi
    ok = rng.random(len(i)) > 0.2
    risks = rng.uniform(0, 0.5, B), rng.uniform(0, 0.5, B), rng.uniform(0.1, 2.0, B)
    copies = LinkBatch(i, j, z, x[j], P[j], ok, *risks)
    by_index = LinkBatch.from_predicted(i, j, z, x, P, ok, *risks)
    return x, P, copies, by_index


def assert_same(a, b):
    (xa, Pa, oa), (xb, Pb, ob) = a, b
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(Pa, Pb)
    for f in ("norm", "threshold", "detected", "triggered", "delivered", "fused", "repaired"):
        np.testing.assert_array_equal(getattr(oa, f), getattr(ob, f))


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("kind", ["ckf", "ekf"])
def test_links_by_index_give_the_results_of_copies(backend, kind):
    if backend == "numba" and not kernels.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    x, P, copies, by_index = swarm_links(0)
    params = CLParams(threshold_innovation=ThresholdInnovation.LAST_SENT)
    filt = make_filter(kind)
    memories = LinkMemory(len(x)), LinkMemory(len(x))
    with kernels.use_backend(backend):
        a = correct(filt, x, P, copies, params, memories[0])
        b = correct(filt, x, P, by_index, params, memories[1])
    assert a[2].compiled == b[2].compiled == (backend == "numba")
    assert_same(a, b)
    np.testing.assert_array_equal(memories[0].x, memories[1].x)
    np.testing.assert_array_equal(memories[0].P, memories[1].P)
    if backend == "numba":  # the kernel read by index: nothing was gathered
        assert by_index.neighbour_rows()[0] is not None


@needs_numba
def test_a_reader_of_x_nb_gets_a_private_copy_that_the_kernel_then_uses():
    """An attacker reads and alters ``x_nb`` (``dataclasses.replace``): the batch then
    holds the altered copy, and both paths fuse with it."""
    x, P, copies, by_index = swarm_links(1)
    assert by_index.neighbour_rows()[0] is not None
    np.testing.assert_array_equal(by_index.x_nb, copies.x_nb)  # gathered on first read
    np.testing.assert_array_equal(by_index.P_nb, copies.P_nb)
    assert by_index.neighbour_rows()[0] is None
    fresh = swarm_links(1)[3]
    tampered_x = fresh.x_nb + np.array([0.3, -0.2, 0.0])
    altered = dataclasses.replace(fresh, x_nb=tampered_x)
    reference = dataclasses.replace(copies, x_nb=tampered_x)
    assert altered.neighbour_rows()[0] is None
    filt, params = make_filter("ckf"), CLParams()
    with kernels.use_backend("numba"):
        assert_same(correct(filt, x, P, altered, params), correct(filt, x, P, reference, params))
    x[:] = 0.0  # the predicted arrays changed after the copy: the copy keeps its values
    np.testing.assert_array_equal(altered.x_nb, tampered_x)


def test_neighbour_states_out_of_range_go_to_the_reference_path():
    x, P, _, by_index = swarm_links(2)
    bad = dataclasses.replace(
        by_index, x_nb=None, P_nb=None, neighbours=NeighbourStates(by_index.j, x[:3], P[:3])
    )
    with pytest.raises(IndexError):  # the reference path's gather names the problem
        correct(make_filter("ckf"), x, P, bad, CLParams())


def _brute_force(p, team, radius):
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    near = (d2 <= radius * radius) & (team[:, None] == team[None, :])
    np.fill_diagonal(near, False)
    return np.nonzero(near)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cell_lists_find_the_kdtree_pairs(seed):
    rng = np.random.default_rng(seed)
    B = 900
    p = rng.uniform(-7, 12, (B, 2))
    team = np.repeat(np.arange(3), B // 3)
    # Robots on an integer lattice with the radius as spacing: pairs at exactly the radius,
    # and coincident robots.
    p[:200] = np.column_stack([np.arange(200) % 14, np.arange(200) // 14]).astype(float)
    p[200:210] = p[0]
    for radius in (1.0, 0.37, 2.5):
        kd = radius_links(p, team, radius, "kdtree")
        cells = radius_links(p, team, radius, "cells")
        np.testing.assert_array_equal(kd[0], cells[0])
        np.testing.assert_array_equal(kd[1], cells[1])
    np.testing.assert_array_equal(np.vstack(cells), np.vstack(_brute_force(p, team, 2.5)))


def test_cell_lists_on_a_sparse_grid_and_degenerate_input():
    # Two clusters far apart: more squares than robots (the hashed table).
    rng = np.random.default_rng(3)
    p = np.vstack([rng.uniform(0, 3, (40, 2)), 1e7 + rng.uniform(0, 3, (40, 2))])
    team = np.zeros(80, np.int64)
    kd = radius_links(p, team, 1.0, "kdtree")
    cells = radius_links(p, team, 1.0, "cells")
    np.testing.assert_array_equal(np.vstack(kd), np.vstack(cells))
    # A radius of zero links coincident robots only; an unknown method is refused.
    q = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    i, j = radius_links(q, np.zeros(3, np.int64), 0.0, "cells")
    assert list(zip(i, j, strict=True)) == [(0, 1), (1, 0)]
    with pytest.raises(ValueError, match="method"):
        radius_links(q, np.zeros(3, np.int64), 1.0, "grid")
