"""World layer: zones, attacks, network, control, batched world determinism."""

import numpy as np
import pytest

from resloc.errors import ConfigError
from resloc.world.attacks import (
    AttackKind,
    LinkScope,
    apply_injection,
    attackable_links,
    injection,
    link_hash_uniform,
)
from resloc.world.control import LeaderPath, lattice_offsets, si_to_unicycle
from resloc.world.network import radius_links
from resloc.world.spec import WorldSpec, ZoneSpec
from resloc.world.world import World
from resloc.world.zones import RiskProfile, Zone, ZoneField, risk_profile


def test_risk_profiles_peak_at_centre_and_vanish_outside():
    s = np.array([0.0, 0.5, 1.0, 1.01, 3.0])
    assert risk_profile(s, RiskProfile.LINEAR).tolist() == [1.0, 0.5, 0.0, 0.0, 0.0]
    assert risk_profile(s, RiskProfile.QUADRATIC).tolist() == [1.0, 0.75, 0.0, 0.0, 0.0]
    assert risk_profile(s, RiskProfile.CONSTANT).tolist() == [1.0, 1.0, 1.0, 0.0, 0.0]
    g = risk_profile(s, RiskProfile.GAUSSIAN)
    assert g[0] == 1.0 and g[1] == pytest.approx(np.exp(-0.5)) and g[3] == 0.0
    st = risk_profile(np.array([0.05, 0.25, 0.45, 0.65, 0.85, 0.99]), RiskProfile.STAIRCASE)
    np.testing.assert_allclose(st, [1.0, 0.8, 0.6, 0.4, 0.2, 0.2])


def test_zone_field_combines_independently_and_honours_tau():
    f = ZoneField([Zone((0.0, 0.0), 1.0, 0.5), Zone((0.0, 0.0), 1.0, 0.5)])
    assert f.risk(np.array([[0.0, 0.0]]))[0] == pytest.approx(0.75)  # 1 - 0.5 * 0.5
    g = ZoneField([Zone((0.0, 0.0), 1.0, 1.0, RiskProfile.LINEAR, tau=0.6)])
    r = g.risk(np.array([[0.3, 0.0], [0.5, 0.0], [2.0, 0.0]]))
    np.testing.assert_allclose(r, [0.7, 0.0, 0.0])
    assert not ZoneField([])


def test_link_hash_is_deterministic_and_uniform():
    i = np.repeat(np.arange(200), 200)
    j = np.tile(np.arange(200), 200)
    u = link_hash_uniform(i, j, 7)
    assert np.array_equal(u, link_hash_uniform(i, j, 7))
    assert not np.array_equal(u, link_hash_uniform(i, j, 8))
    assert 0.0 <= u.min() and u.max() < 1.0
    assert abs(u.mean() - 0.5) < 0.01
    frac = attackable_links(i, j, LinkScope.PARTIAL, 0.3, 7).mean()
    assert abs(frac - 0.3) < 0.01
    assert attackable_links(i, j, LinkScope.FULL, 0.3, 7).all()


def test_injection_kinds():
    rng = np.random.default_rng(0)
    bias = np.array([0.4, 0.8])
    np.testing.assert_array_equal(injection(AttackKind.FIXED, bias, 3, rng), np.tile(bias, (3, 1)))
    r = injection(AttackKind.RANDOM, bias, 10000, rng)
    assert (np.abs(r) <= bias).all() and abs(r.mean(axis=0)).max() < 0.05
    g = injection(AttackKind.GAUSSIAN, bias, 20000, rng)
    np.testing.assert_allclose(g.std(axis=0), bias, rtol=0.05)
    z = apply_injection(np.array([[0.1, 3.0]]), np.array([[-0.3, 0.5]]))
    assert z[0, 0] == pytest.approx(0.2) and z[0, 1] == pytest.approx(3.5 - 2 * np.pi)


def test_radius_links_matches_brute_force_and_separates_teams():
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 1, size=(60, 2))
    team = np.repeat([0, 1, 2], 20)
    p[20:40] = p[:20]  # team 1 sits exactly on team 0: must not be linked to it
    i, j = radius_links(p, team, 0.5)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    want = (d <= 0.5) & (team[:, None] == team[None]) & ~np.eye(60, dtype=bool)
    got = np.zeros_like(want)
    got[i, j] = True
    assert np.array_equal(got, want)
    assert np.all(np.diff(i) >= 0)
    same_i = i[1:] == i[:-1]
    assert np.all(np.diff(j)[same_i] > 0)


def test_leader_path_geometry():
    lp = LeaderPath([[0, 0], [1, 0], "arc", [1, 2], [0, 2]])
    assert lp.length == pytest.approx(1 + np.pi + 1)
    p, h = lp.at(1 + np.pi / 2)  # halfway round the arc: the east-most point
    np.testing.assert_allclose(p, [2.0, 1.0], atol=1e-12)
    assert h == pytest.approx(np.pi / 2)  # moving north (counter-clockwise turn)
    p_end, _ = lp.at(100.0)
    np.testing.assert_allclose(p_end, [0, 2])
    with pytest.raises(ConfigError, match="waypoints"):
        LeaderPath([[0, 0], "arc"])
    with pytest.raises(ConfigError, match="waypoints\\[1\\]"):
        LeaderPath([[0, 0], [1, 2, 3]])


def test_lattice_offsets_make_the_paper_4x4_block():
    off = lattice_offsets(16, 0.25, 0.25)
    assert off.shape == (16, 2)
    assert len(np.unique(off[:, 0])) == 4 and len(np.unique(off[:, 1])) == 4
    assert (off[:, 0] < 0).all()


def test_si_to_unicycle_saturates():
    u = si_to_unicycle(np.zeros((2, 3)), np.array([[5.0, 0.0], [0.0, 5.0]]), 0.05, 0.2, 3.6)
    np.testing.assert_allclose(u, [[0.2, 0.0], [0.0, 3.6]])


def _spec():
    return WorldSpec(
        sdz=(ZoneSpec(center=[0.45, -0.55], radius=0.4),),
        cdz=(ZoneSpec(center=[0.2, 0.45], radius=0.4),),
    )


def test_world_trials_are_independent_of_batching():
    w3 = World(_spec(), trials=3, seed=5)
    w1 = World(_spec(), trials=1, seed=5, first_trial=1)
    x3, _ = w3.initial_estimates()
    x1, _ = w1.initial_estimates()
    np.testing.assert_array_equal(x3[17:34], x1)
    for _ in range(150):
        a, b = w3.step(), w1.step()
    np.testing.assert_array_equal(a.pose[17:34], b.pose)
    sel = (a.i >= 17) & (a.i < 34)
    np.testing.assert_array_equal(a.z[sel], b.z)
    np.testing.assert_array_equal(a.attacked[sel], b.attacked)
    np.testing.assert_array_equal(a.channel_ok[sel], b.channel_ok)
    np.testing.assert_array_equal(a.u_meas[17:34], b.u_meas)


def test_world_respects_limits_and_sensing_radius():
    w = World(_spec(), trials=2, seed=0)
    attacked = 0
    jammed = 0
    for _ in range(900):
        u = w.commands()
        assert np.abs(u[:, 0]).max() <= 0.2 + 1e-12 and np.abs(u[:, 1]).max() <= 3.6 + 1e-12
        s = w.step()
        d = np.linalg.norm(s.pose[s.i, :2] - s.pose[s.j, :2], axis=1)
        assert (d <= 1.0).all()
        attacked += s.attacked.sum()
        jammed += (~s.channel_ok).sum()
        # Only robots with sensing risk can be attacked; only risky robots get jammed.
        assert (s.risk_s[s.i][s.attacked] > 0).all()
        assert (s.risk_c[s.i][~s.channel_ok] > 0).all()
        assert (s.lambda2 > 0).all()
    assert attacked > 0 and jammed > 0


def test_world_without_zones_has_no_attacks():
    w = World(WorldSpec(), trials=1, seed=0)
    for _ in range(50):
        s = w.step()
        assert not s.attacked.any() and s.channel_ok.all()
