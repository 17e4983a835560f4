"""Attacker models (issue 6): stealthy (detector-aware) injection and replay."""

from __future__ import annotations

import math

import numpy as np
import pytest

from resloc.cl.cusum import chi2_gate
from resloc.cl.detector import InnovationNorm, innovation_norm
from resloc.experiments.config import default_scenario
from resloc.experiments.runner import run_scenario
from resloc.filters.update import innovation
from resloc.world.adversary import (
    ReplayBuffer,
    StealthKnowledge,
    largest_stealthy_step,
    stealthy_tamper,
)
from resloc.world.attacks import AttackKind, injection
from resloc.world.world import World

STD = np.array([0.005, 0.05])


def test_largest_step_hits_the_bound(rng, random_spd):
    nu = rng.normal(size=(100, 2)) * 0.3
    W = random_spd(rng, 100, 2)
    d = np.array([0.6, 0.8])
    c2 = np.full(100, 4.0)
    a = largest_stealthy_step(nu, d, W, c2)
    stat = np.einsum("ei,eij,ej->e", nu + a[:, None] * d, W, nu + a[:, None] * d)
    inside = np.einsum("ei,eij,ej->e", nu, W, nu) <= 4.0
    np.testing.assert_allclose(stat[inside], 4.0, rtol=1e-9)
    assert np.all(a[~inside] == 0.0)
    assert np.all(a >= 0.0)


@pytest.mark.parametrize("norm", list(InnovationNorm))
def test_stealthy_tamper_sits_at_margin_of_the_gate(rng, random_spd, norm):
    E = 50
    z_hat = np.column_stack([rng.uniform(0.3, 1.0, E), rng.uniform(-3, 3, E)])
    z = z_hat + rng.normal(size=(E, 2)) * STD
    S = random_spd(rng, E, 2, scale=1e-3) + np.diag(STD**2)
    rho = {"euclidean": 0.5, "scaled": 8.0, "nis": math.sqrt(chi2_gate(0.01))}[norm.value]
    attacked = np.ones(E, bool)
    attacked[::5] = False
    tamper = stealthy_tamper(
        z,
        attacked,
        np.zeros(E, int),
        [1.0, 0.0],
        0.9,
        np.array([10.0, 10.0]),
        True,
        norm,
        rho,
        STD,
    )
    rows = np.arange(E)
    out = tamper(rows, z_hat, S)
    np.testing.assert_array_equal(out[~attacked], z[~attacked])
    stat = innovation_norm(innovation(out, z_hat), S, norm, STD)
    honest = innovation_norm(innovation(z, z_hat), S, norm, STD)
    ok = attacked & (honest <= 0.9 * rho)
    np.testing.assert_allclose(stat[ok], 0.9 * rho, rtol=1e-8)
    assert np.all(out[ok, 0] > z[ok, 0])  # along +range


def test_stealthy_tamper_respects_cusum_and_cap(rng):
    E = 20
    z_hat = np.column_stack([np.full(E, 0.5), np.zeros(E)])
    z = z_hat.copy()
    S = np.broadcast_to(np.diag([1e-4, 1e-2]), (E, 2, 2)).copy()
    attacked = np.ones(E, bool)
    args = (z, attacked, np.zeros(E, int), [1.0, 0.0], 0.9, np.array([10.0, 1.0]), True)
    full = stealthy_tamper(*args, "nis", 3.0, STD, 4.0, StealthKnowledge.FULL)
    gate = stealthy_tamper(*args, "nis", 3.0, STD, 4.0, StealthKnowledge.GATE)
    rows = np.arange(E)
    nis_full = ((full(rows, z_hat, S) - z_hat)[:, 0] ** 2) / 1e-4
    nis_gate = ((gate(rows, z_hat, S) - z_hat)[:, 0] ** 2) / 1e-4
    np.testing.assert_allclose(nis_full, 0.9 * 4.0)
    np.testing.assert_allclose(nis_gate, (0.9 * 3.0) ** 2)
    capped = stealthy_tamper(
        z,
        attacked,
        np.zeros(E, int),
        [1.0, 0.0],
        0.9,
        np.array([0.001, 1.0]),
        False,
        "nis",
        3.0,
        STD,
    )
    np.testing.assert_allclose(capped(rows, z_hat, S)[:, 0] - z_hat[:, 0], 0.001)


def test_additive_injection_rejects_new_kinds(rng):
    with pytest.raises(ValueError, match="not an additive"):
        injection(AttackKind.STEALTHY, np.ones(2), 3, rng)


def test_replay_buffer():
    buf = ReplayBuffer(2, 10)
    i, j = np.array([0, 1]), np.array([1, 0])
    found, _ = buf.replayed(i, j)
    assert not found.any()
    buf.record(i, j, np.array([[1.0, 0.1], [2.0, 0.2]]))
    buf.record(np.array([0]), np.array([1]), np.array([[3.0, 0.3]]))
    found, z = buf.replayed(np.array([1, 0, 2]), np.array([0, 1, 0]))
    np.testing.assert_array_equal(found, [True, True, False])
    np.testing.assert_allclose(z[:2], [[2.0, 0.2], [1.0, 0.1]])
    with pytest.raises(ValueError):
        ReplayBuffer(0, 3)


def _world(kind: str, **attack):
    zone = [{"center": [-0.8, -0.9], "radius": 0.6, "peak": 0.9}]
    sc = default_scenario().replace(
        **{"sdz": zone, "cdz": [], "attack.kind": kind, "team.robots": 6, **attack}
    )
    return World(sc.world, 1, 3)


def test_world_replay_uses_the_links_old_honest_measurement():
    delay = 5
    replay = _world("replay", **{"attack.replay_delay": delay})
    honest = _world("fixed", **{"attack.bias": [0.0, 0.0]})  # same draws, nothing added
    hist = []
    n_att = 0
    for _ in range(40):
        a, h = replay.step(), honest.step()
        hist.append(h)
        if a.attacked.any():
            old = hist[-1 - delay]
            key_old = old.i * 1000 + old.j
            for e in np.flatnonzero(a.attacked):
                pos = np.flatnonzero(key_old == a.i[e] * 1000 + a.j[e])
                np.testing.assert_allclose(a.z[e], old.z[pos[0]])
                n_att += 1
        np.testing.assert_allclose(a.z[~a.attacked], h.z[~a.attacked])
    assert n_att > 0


def test_world_stealthy_marks_but_does_not_change():
    w, h = _world("stealthy"), _world("fixed", **{"attack.bias": [0.0, 0.0]})
    for _ in range(10):
        a, b = w.step(), h.step()
        np.testing.assert_array_equal(a.attacked, b.attacked)
        np.testing.assert_allclose(a.z, b.z)


def test_runner_stealthy_passes_the_paper_detector():
    """End to end: against the raw-norm gate the stealthy attacker is (almost) never caught,
    yet it moves the estimates."""
    zone = [{"center": [-0.8, -0.9], "radius": 0.6, "peak": 0.9}]
    base = default_scenario().replace(
        **{
            "sdz": zone,
            "cdz": [],
            "team.robots": 5,
            "run.steps": 60,
            "run.filters": ["ekf"],
            "run.dead_reckoning": False,
        }
    )
    st = run_scenario(base.replace(**{"attack.kind": "stealthy", "attack.bias": [0.3, 0.6]}))
    s = st.summary()["ekf"]
    assert s["attacked_rate"] > 0.1
    assert s["detector_recall"] < 0.05
    clean = run_scenario(base.replace(**{"sdz": []})).summary()["ekf"]
    assert s["msle_mean"] > 10 * clean["msle_mean"]


def test_largest_linear_step_brute_force(rng):
    from resloc.world.adversary import largest_linear_step

    w0 = rng.normal(size=(200, 2)) * 0.4
    v = rng.normal(size=(200, 2))
    c = np.full(200, 0.45)
    a = largest_linear_step(w0, v, c)
    grid = np.linspace(0.0, 20.0, 20001)
    for e in range(200):
        ok = (np.abs(w0[e][None] + grid[:, None] * v[e][None]) <= c[e] + 1e-12).all(axis=1)
        best = grid[ok].max() if ok[0] else 0.0
        assert abs(min(a[e], 20.0) - best) <= 2e-3, e


def test_stealthy_tamper_respects_the_mean_shift_test(rng):
    from resloc.cl.cusum import whiten

    E = 50
    z_hat = np.column_stack([np.full(E, 0.5), np.zeros(E)])
    S = np.broadcast_to(np.diag([1e-4, 1e-2]), (E, 2, 2)).copy()
    z = z_hat + rng.normal(size=(E, 2)) * np.sqrt([1e-4, 1e-2])
    tamper = stealthy_tamper(
        z, np.ones(E, bool), np.zeros(E, int), [1.0, 0.0], 0.9, np.array([10.0, 1.0]),
        True, "nis", 3.0, STD, 3.0, StealthKnowledge.FULL, 0.5,
    )  # fmt: skip
    out = tamper(np.arange(E), z_hat, S)
    w_honest, w = whiten(z - z_hat, S), whiten(out - z_hat, S)
    inside = (np.abs(w_honest) <= 0.45).all(axis=1)
    assert (np.abs(w[inside]) <= 0.45 + 1e-9).all()
    assert (out[inside, 0] >= z[inside, 0] - 1e-15).all()  # pushes along +range only
    np.testing.assert_allclose(out[~inside], z[~inside], atol=1e-12)  # abstains otherwise
    assert inside.any() and (~inside).any()
