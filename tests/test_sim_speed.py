"""What makes the simulation and its start-up faster without changing a number: outcome
counts in bulk, dense graph work for team-sized graphs (no scipy), pairwise links, the
leader path's constants, and the imports a run does not need until it steps."""

from __future__ import annotations

import itertools
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse.csgraph as csgraph

from resloc.cl import graph
from resloc.cl.links import LinkOutcome
from resloc.experiments import metrics, runner
from resloc.experiments.config import default_scenario
from resloc.experiments.outcomes import COUNTED, OutcomeCounter, per_group_counts
from resloc.experiments.recording import pack_outcomes
from resloc.world import world as world_module
from resloc.world.control import LeaderPath
from resloc.world.network import PAIRWISE_MAX, radius_links

# ----------------------------------------------------------------------------- outcome counts
T, N, STEPS = 3, 4, 19


def _per_step_counts(team_i, out, att, T):
    """The per-step bincounts the runner made before the counts were computed in bulk."""

    def count(mask):
        return np.bincount(team_i, weights=mask, minlength=T).astype(np.int64)

    det = out.detected
    return {
        "triggered": count(out.triggered),
        "delivered": count(out.delivered),
        "detected": count(det),
        "failed": count(out.triggered & ~out.delivered),
        "fused": count(out.fused),
        "attacked_fused": count(out.fused & att),
        "tp": count(det & att),
        "fp": count(det & ~att),
        "fn": count(~det & att),
        "tn": count(~det & ~att),
        "repairs": count(out.repaired),
    }


def _random_step(rng, empty=False):
    B = T * N
    pairs = [(a, b) for a in range(B) for b in range(B) if a != b and a // N == b // N]
    keep = rng.random(len(pairs)) < (0.0 if empty else 0.6)
    i = np.array([p[0] for p, k in zip(pairs, keep, strict=True) if k], dtype=np.int64)
    E = len(i)
    flags = rng.random((6, E)) < 0.4
    out = LinkOutcome(np.zeros(E), np.zeros(E), *flags[:5])
    return i, out, flags[5]


def _records(steps):
    series = {k: np.full((steps, T), np.nan) for k in runner.SERIES}
    totals = {k: np.zeros(T, np.int64) for k in runner.TOTALS}
    return series, totals, np.zeros((steps, N), np.int8), []


@pytest.mark.parametrize("capacity", [1, 5, 256])
@pytest.mark.parametrize("acks", [None, "ack", "delivery_ack"])
def test_outcome_counter_equals_the_per_step_counts(capacity, acks):
    rng = np.random.default_rng(capacity)
    series, totals, raster, flags_log = _records(STEPS)
    counter = OutcomeCounter(series, totals, raster, flags_log, T, N, acks)
    counter.MAX_ROWS = capacity
    want_series, want_totals, want_raster, want_log = _records(STEPS)
    for k in range(STEPS):
        i, out, att = _random_step(rng, empty=k == 3)
        team_i = i // N
        cand = np.bincount(team_i, minlength=T)
        att_n = np.bincount(team_i, weights=att, minlength=T)
        dead_reckoning = k == 7  # a step without outcomes records the candidates only
        counter.add(k, None if dead_reckoning else out, i, team_i, att, cand, att_n)
        want_series["candidates"][k], want_series["attacked"][k] = cand, att_n
        want_totals["candidates"] += cand
        want_totals["attacked"] += att_n.astype(np.int64)
        if dead_reckoning:
            continue
        counts = _per_step_counts(team_i, out, att, T)
        for key in ("triggered", "delivered", "detected"):
            want_series[key][k] = counts[key]
        for key in COUNTED:
            want_totals[key] += counts[key]
        if acks:
            want_totals[f"{acks}_links"] += counts["fused"]
            fusing = np.unique(i[out.fused]) // N
            want_totals[f"{acks}_frames"] += np.bincount(fusing, minlength=T)
        own = i < N
        want_raster[k] = np.bincount(i[own], weights=out.triggered[own], minlength=N)
        want_log.append(
            pack_outcomes(
                *(f[own] for f in (out.detected, out.triggered, out.delivered, out.fused))
            )
        )
    assert not counter.pending  # the last row flushed the buffer
    for key in want_series:
        np.testing.assert_array_equal(series[key], want_series[key], err_msg=key)
    for key in want_totals:
        np.testing.assert_array_equal(totals[key], want_totals[key], err_msg=key)
        assert totals[key].dtype == np.int64
    np.testing.assert_array_equal(raster, want_raster)
    np.testing.assert_array_equal(np.concatenate(flags_log), np.concatenate(want_log))
    assert any(t.any() for k, t in totals.items() if k in COUNTED)


def test_outcome_counter_flush_keeps_the_order_of_the_link_log():
    """A stopped estimator flushes before its zero rows are appended (runner: record)."""
    rng = np.random.default_rng(1)
    series, totals, raster, flags_log = _records(STEPS)
    counter = OutcomeCounter(series, totals, raster, flags_log, T, N)
    i, out, att = _random_step(rng)
    counter.add(0, out, i, i // N, att, np.zeros(T, np.int64), np.zeros(T))
    assert not flags_log  # buffered
    counter.flush()
    flags_log.append(np.zeros(3, np.uint8))
    assert len(flags_log) == 2 and len(flags_log[0]) == int((i < N).sum())


def test_per_group_counts_is_bincount_per_row():
    rng = np.random.default_rng(2)
    for groups in (1, 2, 7, 7):
        masks = rng.random((5, 40)) < 0.5
        group = rng.integers(0, groups, 40)
        if groups == 7:
            group.sort()  # the sorted path (a group may be empty)
        want = np.stack([np.bincount(group, weights=m, minlength=groups) for m in masks])
        np.testing.assert_array_equal(per_group_counts(masks, group, groups), want)


@pytest.mark.parametrize("n", [0, 1, 9, 300])
def test_pack_outcomes_sets_bit_b_from_flag_b(n):
    rng = np.random.default_rng(n)
    flags = [rng.random(n) < 0.5 for _ in range(6)]
    want = np.zeros(n, np.uint8)
    for bit, f in enumerate(flags):
        want |= f.astype(np.uint8) << bit
    got = pack_outcomes(*flags)
    assert got.dtype == np.uint8 and got.shape == (n,)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="8 flags"):
        pack_outcomes(*([flags[0]] * 9))


# ----------------------------------------------------------------------------- graphs, links
def _random_graph(rng, n):
    p = rng.uniform(0, rng.uniform(1, 2 * np.sqrt(n) + 1), (n, 2))
    d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
    i, j = np.nonzero((d <= 1.0) & ~np.eye(n, dtype=bool))
    if rng.random() < 0.3:  # one direction per edge
        i, j = i[i < j], j[i < j]
    return i, j


def _scipy_component_lambda2(i, j, n):
    """The definition: each component's dense block of the sparse Laplacian, nodes in
    increasing order, through the library's dense eigensolver."""
    L = graph.laplacian(i, j, n)
    labels = csgraph.connected_components(L, directed=False)[1]
    dense = L.toarray()
    out = np.zeros(n)
    for c in np.unique(labels):
        nodes = np.flatnonzero(labels == c)
        if len(nodes) > 1:
            out[nodes] = graph._dense_lambda2(dense[np.ix_(nodes, nodes)][None])[0]
    return out


def test_small_graph_lambda2_equals_the_sparse_laplacian_blocks_exactly():
    rng = np.random.default_rng(3)
    sizes = [*rng.integers(1, 40, 80), graph.DENSE_MAX - 1, graph.DENSE_MAX]
    for n in map(int, sizes):
        i, j = _random_graph(rng, n)
        got = graph.component_lambda2(i, j, n)
        np.testing.assert_array_equal(got, _scipy_component_lambda2(i, j, n))
        labels = graph.component_labels(i, j, n)
        ref = csgraph.connected_components(graph.laplacian(i, j, n), directed=False)[1]
        # the same partition (numbered differently is fine)
        assert len(set(zip(labels, ref, strict=True))) == len(set(ref)) == len(set(labels))
        np.testing.assert_array_equal(
            graph.dense_laplacian(i, j, n), graph.laplacian(i, j, n).toarray()
        )


def test_small_graph_global_mode_per_group():
    rng = np.random.default_rng(4)
    n = 30
    group = np.repeat(np.arange(3), 10)
    i, j = _random_graph(rng, n)
    same = group[i] == group[j]
    i, j = i[same], j[same]
    got = graph.component_lambda2(i, j, n, "global", group=group)
    for g in range(3):
        nodes = np.flatnonzero(group == g)
        L = graph.laplacian(i, j, n).toarray()[np.ix_(nodes, nodes)]
        np.testing.assert_array_equal(got[nodes], graph.algebraic_connectivity(L))
    with pytest.raises(ValueError, match="mode"):
        graph.component_lambda2(i, j, n, "nope")


def test_pairwise_links_equal_the_kd_tree_and_cell_lists():
    rng = np.random.default_rng(5)
    for _ in range(300):
        trials, robots = int(rng.integers(1, 5)), int(rng.integers(1, 33))
        p = rng.uniform(-3, 3, (trials * robots, 2)) * rng.uniform(0.1, 3)
        if rng.random() < 0.4:
            p = np.round(p, 1)  # pairs exactly at the radius
        team = np.repeat(np.arange(trials), robots)
        radius = float(rng.choice([0.3, 0.5, 1.0]))
        want = radius_links(p, team, radius, "kdtree")
        for method in ("pairs", "cells", "auto"):
            got = radius_links(p, team, radius, method)
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
                assert a.dtype == np.int64
    assert PAIRWISE_MAX >= 17  # a team of the paper's size takes the pairwise test


def test_world_lambda2_is_solved_only_when_the_graph_changed(monkeypatch):
    """The world keeps ``lambda2`` while the communication graph is unchanged, and the kept
    values equal solving every step."""
    calls = []
    real = world_module.component_lambda2

    def counted(i, j, n, *args, **kwargs):
        calls.append((i.copy(), j.copy()))
        return real(i, j, n, *args, **kwargs)

    monkeypatch.setattr(world_module, "component_lambda2", counted)
    scenario = default_scenario()
    world = world_module.World(scenario.world, 2, 0, "component")
    steps = [world.step() for _ in range(60)]
    edges = []
    for ws in steps:
        p = ws.pose[:, :2]
        ok = np.hypot(*(p[ws.i] - p[ws.j]).T) <= scenario.world.sensing.comm_radius
        np.testing.assert_array_equal(ok, ws.in_comm)
        edges.append((ws.i[ok], ws.j[ok]))
        fresh = real(ws.i[ok], ws.j[ok], world.B, "component", group=world.team)
        np.testing.assert_array_equal(ws.lambda2, fresh)
    changes = 1 + sum(
        not (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]))
        for a, b in itertools.pairwise(edges)
    )
    assert len(calls) == changes < len(steps)


# ----------------------------------------------------------------------------- leader path
def _reference_at(path, s):
    """LeaderPath.at as first written (numpy scalar calls per query)."""
    s = float(np.clip(s, 0.0, path.length))
    k = int(min(np.searchsorted(path.cumulative, s, side="right") - 1, len(path.kinds) - 1))
    a, b = path.points[k], path.points[k + 1]
    t = (s - path.cumulative[k]) / max(path.lengths[k], 1e-12)
    if path.kinds[k] == "line":
        d = b - a
        return a + t * d, float(np.arctan2(d[1], d[0]))
    centre = 0.5 * (a + b)
    r = 0.5 * float(np.linalg.norm(b - a))
    phi0 = float(np.arctan2(a[1] - centre[1], a[0] - centre[0]))
    phi = phi0 + np.pi * t
    return centre + r * np.array([np.cos(phi), np.sin(phi)]), phi + np.pi / 2.0


@pytest.mark.parametrize(
    "waypoints",
    [
        default_scenario().world.motion.waypoints,
        [[0, 0], "arc", [2, 1], [3, -1], "arc", [0, 0]],
        [[1, 1], [1, 1], [2, 2]],
    ],
)
def test_leader_path_positions_equal_the_direct_formula(waypoints):
    path = LeaderPath(waypoints)
    rng = np.random.default_rng(6)
    for s in [*rng.uniform(-1, path.length + 1, 2000), *path.cumulative, 0.0, path.length]:
        p, heading = path.at(s)
        p_ref, heading_ref = _reference_at(path, s)
        np.testing.assert_array_equal(p, p_ref)
        assert heading == heading_ref


# ----------------------------------------------------------------------------- start-up
_RUN_PROBE = """
import sys
import resloc.cli.app
from resloc.cli import run
from resloc.experiments import metrics, runner
from resloc.experiments.config import default_scenario
from resloc.experiments.run_files import save_run
loaded = lambda: sorted(m for m in ("numba", "scipy", "scipy.sparse", "scipy.spatial",
    "scipy.special", "matplotlib") if m in sys.modules)
print("IMPORT=" + ",".join(loaded()))
runner.run_scenario(default_scenario().replace(**{"run.steps": 5}))
print("RUN=" + ",".join(loaded()))
"""


def test_a_team_sized_run_needs_no_scipy_graph_modules_and_numba_only_to_step():
    proc = subprocess.run(
        [sys.executable, "-c", _RUN_PROBE], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    lines = dict(line.split("=", 1) for line in proc.stdout.splitlines() if "=" in line)
    assert lines["IMPORT"] == ""  # the command, the runner and the writers: none of them
    ran = set(lines["RUN"].split(","))
    assert "numba" in ran  # loaded by the first kernel
    assert not ran & {"scipy.sparse", "scipy.spatial", "scipy.special", "matplotlib"}


# ----------------------------------------------------------------------------- metrics
def test_pair_distances_equal_numpys_norm_and_shared_truth_changes_nothing():
    rng = np.random.default_rng(7)
    p = rng.normal(size=(4, 9, 2)) * 3.0
    want = np.linalg.norm(p[:, :, None, :] - p[:, None, :, :], axis=-1)
    np.testing.assert_array_equal(metrics.pair_distances(p), want)
    trials, robots, steps = 2, 5, 11
    truth = [rng.normal(size=(trials * robots, 3)) for _ in range(steps)]
    shared = metrics.TruthDistances()
    records = []
    for truth_cache in (None, shared, shared):  # alone, then two sharing one truth cache
        series = {k: np.full((steps, trials), np.nan) for k in ("msle", "rmse", "nees", "nees_rel")}
        totals = {
            k: np.zeros(trials, np.int64)
            for k in ("nees_samples", "nees_exceed", "nees_rel_exceed")
        }
        recorder = metrics.AccuracyRecorder(series, totals, trials, robots, truth_cache)
        recorder.capacity = 4
        est_rng = np.random.default_rng(8)
        for k, pose in enumerate(truth):
            x = pose + 0.1 * est_rng.normal(size=pose.shape)
            recorder.add(k, pose, x, np.broadcast_to(0.01 * np.eye(3), (len(pose), 3, 3)))
        records.append(series)
    for key in records[0]:
        np.testing.assert_array_equal(records[1][key], records[0][key])
        np.testing.assert_array_equal(records[2][key], records[0][key])
