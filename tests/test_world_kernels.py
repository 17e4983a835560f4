"""The world step's compiled twin (resloc.world.kernels) equals its numpy specification
bit for bit, piece by piece and over whole runs of every world option."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from resloc.cl.backend import HAVE_NUMBA, use_backend
from resloc.experiments.config import default_scenario
from resloc.models.measurement import range_bearing
from resloc.models.motion import unicycle_step
from resloc.world.attacks import AttackKind, LinkScope
from resloc.world.network import PAIRWISE_MAX, radius_links
from resloc.world.spec import ChannelRule, FormationFrame, ZoneSpec
from resloc.world.world import World, compiled_world
from resloc.world.zones import RiskProfile, Zone, ZoneField

pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="the compiled twin needs numba")

kernels = pytest.importorskip("resloc.world.kernels")


def _world_spec(**changes):
    """The default scenario's world with ``changes`` (dotted: ``attack.kind``)."""
    spec = default_scenario().world
    for dotted, value in changes.items():
        section, name = dotted.split(".") if "." in dotted else (None, dotted)
        if section is None:
            spec = dataclasses.replace(spec, **{name: value})
        else:
            part = dataclasses.replace(getattr(spec, section), **{name: value})
            spec = dataclasses.replace(spec, **{section: part})
    return spec


def _zones(profile, tau=0.0, peak=1.0):
    return (
        ZoneSpec(center=[0.45, -0.55], radius=0.4, peak=peak, profile=profile, tau=tau),
        ZoneSpec(center=[0.6, -0.3], radius=0.5, peak=0.7, profile=profile, tau=tau),
    )


WORLDS = {
    "default": {},
    "fixed attack, leader frame, either channel": {
        "attack.kind": AttackKind.FIXED,
        "motion.formation": FormationFrame.LEADER,
        "attack.channel": ChannelRule.EITHER,
    },
    "gaussian attack, partial links, quadratic zones": {
        "attack.kind": AttackKind.GAUSSIAN,
        "attack.links": LinkScope.PARTIAL,
        "sdz": _zones(RiskProfile.QUADRATIC, tau=0.2),
        "cdz": _zones(RiskProfile.STAIRCASE),
    },
    "replay, constant and gaussian zones": {
        "attack.kind": AttackKind.REPLAY,
        "sdz": _zones(RiskProfile.CONSTANT, peak=0.3),
        "cdz": _zones(RiskProfile.GAUSSIAN),
    },
    "no zones": {"sdz": (), "cdz": ()},
    "stealthy, small team": {"attack.kind": AttackKind.STEALTHY, "team.robots": 5},
}

FIELDS = ("pose", "u_meas", "i", "j", "z", "attacked", "channel_ok", "risk_s", "risk_c")


@pytest.mark.parametrize("name", list(WORLDS))
@pytest.mark.parametrize("trials", [1, 3])
def test_compiled_world_steps_equal_the_numpy_world_exactly(name, trials):
    spec = _world_spec(**WORLDS[name])
    with use_backend("numpy"):
        reference = World(spec, trials=trials, seed=3)
    with use_backend("numba"):
        compiled = World(spec, trials=trials, seed=3)
    assert reference._compiled is None
    assert compiled._compiled is kernels  # the compiled path runs
    for _ in range(120):
        want, got = reference.step(), compiled.step()
        for field in FIELDS:
            a, b = getattr(want, field), getattr(got, field)
            assert a.dtype == b.dtype, field
            np.testing.assert_array_equal(a, b, err_msg=field)
        np.testing.assert_array_equal(want.in_comm, got.in_comm)
        np.testing.assert_array_equal(want.lambda2, got.lambda2)
    assert len(want.i) > 0  # the teams saw each other


def test_large_teams_and_the_numpy_backend_keep_the_numpy_world():
    with use_backend("numba"):
        assert compiled_world(PAIRWISE_MAX) is kernels
        assert compiled_world(PAIRWISE_MAX + 1) is None
    with use_backend("numpy"):
        assert compiled_world(17) is None


def test_move_team_equals_the_commands_and_the_unicycle():
    spec = _world_spec(**{"motion.formation": FormationFrame.LEADER})
    with use_backend("numpy"):
        world = World(spec, trials=2, seed=1)
    rng = np.random.default_rng(0)
    m = spec.motion
    for k in range(40):
        world.k = k
        world.pose = world.pose + rng.normal(scale=0.3, size=world.pose.shape)
        u_want = world.commands()
        pose_want = unicycle_step(world.pose, u_want, world.dt)
        leader, offsets, _ = world._leader_and_offsets((k + 1) * world.dt)
        u, pose = np.empty((world.B, 2)), np.empty((world.B, 3))
        kernels.move_team(
            world.pose, leader, offsets, m.projection, m.gain, m.v_max, m.omega_max, world.dt,
            u, pose,
        )  # fmt: skip
        np.testing.assert_array_equal(u, u_want)
        np.testing.assert_array_equal(pose, pose_want)


@pytest.mark.parametrize("n, teams", [(2, 1), (17, 1), (9, 4), (40, 3)])
def test_team_links_equal_radius_links_and_the_ranges(n, teams):
    rng = np.random.default_rng(n * teams)
    for scale in (0.3, 1.0, 3.0):
        pose = rng.normal(scale=scale, size=(n * teams, 3))
        team = np.repeat(np.arange(teams), n)
        for method in ("pairs", "kdtree", "cells"):
            i_want, j_want = radius_links(pose[:, :2], team, 1.0, method=method)
            i, j, dx, dy, distance, in_comm, counts = kernels.team_links(pose, n, 1.0, 0.7)
            np.testing.assert_array_equal(i, i_want)
            np.testing.assert_array_equal(j, j_want)
        np.testing.assert_array_equal(distance, range_bearing(pose[i], pose[j])[:, 0])
        np.testing.assert_array_equal(dx, pose[j, 0] - pose[i, 0])
        np.testing.assert_array_equal(dy, pose[j, 1] - pose[i, 1])
        p = pose[:, :2]
        np.testing.assert_array_equal(in_comm, np.hypot(*(p[i] - p[j]).T) <= 0.7)
        np.testing.assert_array_equal(counts, np.bincount(team[i], minlength=teams))


def test_noisy_measurements_equal_range_bearing_plus_noise():
    rng = np.random.default_rng(4)
    pose = rng.normal(scale=2.0, size=(12, 3))
    pose[:, 2] = rng.uniform(-10, 10, 12)  # headings of any magnitude
    i, j = radius_links(pose[:, :2], np.zeros(12, np.int64), 5.0)
    noise = rng.normal(size=(len(i), 2)) * 40.0  # large: negative ranges, many wraps
    std = np.array([0.05, 0.2])
    want = range_bearing(pose[i], pose[j]) + noise * std
    want[:, 0] = np.abs(want[:, 0])
    want[:, 1] = np.mod(want[:, 1] + np.pi, 2.0 * np.pi) - np.pi
    dx, dy = pose[j, 0] - pose[i, 0], pose[j, 1] - pose[i, 1]
    got = kernels.noisy_measurements(np.hypot(dx, dy), np.arctan2(dy, dx), pose, i, noise, std)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("profile", [p for p in RiskProfile if p in kernels.PROFILE_CODE])
def test_zone_risk_equals_the_zone_field(profile):
    field = ZoneField(
        [
            Zone((0.0, 0.0), 1.0, 0.9, profile, 0.0),
            Zone((0.5, 0.2), 0.7, 1.0, profile, 0.35),
            Zone((-1.0, 0.4), 2.0, 0.4, profile, 0.1),
        ]
    )
    p = np.random.default_rng(2).uniform(-3.0, 3.0, size=(4000, 2))
    p[:3] = [[0.0, 0.0], [0.5, 0.2], [1.0, 0.0]]  # centres and an edge
    compiled = kernels.zone_arrays(field)
    assert compiled is not None
    np.testing.assert_array_equal(compiled.risk(p), field.risk(p))


def test_gaussian_zones_and_empty_fields_have_no_compiled_form():
    gaussian = ZoneField([Zone((0.0, 0.0), 1.0, 1.0, RiskProfile.GAUSSIAN)])
    assert kernels.zone_arrays(gaussian) is None  # numpy's exp and numba's differ in bits
    assert kernels.zone_arrays(ZoneField([])) is None
