"""Compiled twin of the world's step (numba, the optional extra ``fast``).

At a team's size the numpy world step is some fifty small array operations, each a few
microseconds of dispatch for a few dozen numbers. These kernels make the same arithmetic
in a handful of calls, operation for operation, so their results are bit-identical to the
numpy functions they twin (tested exactly):

==========================  =================================================================
kernel                      numpy twin
==========================  =================================================================
:func:`move_team`           ``World.commands`` (formation control, eq. (1) of the
                            follower's law), :func:`~resloc.world.control.si_to_unicycle` and
                            :func:`~resloc.models.motion.unicycle_step` (eq. (2))
:func:`team_links`          :func:`~resloc.world.network.radius_links` (team-sized blocks of
                            every pair), the ranges of
                            :func:`~resloc.models.measurement.range_bearing` and the radio
                            range test
:func:`noisy_measurements`  :func:`~resloc.models.measurement.range_bearing` (eq. (3)) plus
                            the sensor noise, ``|range|`` and the wrapped bearing
:func:`zone_risk`           :meth:`ZoneField.risk <resloc.world.zones.ZoneField.risk>`
                            (eqs. (4), (7)) for every profile but ``gaussian``
==========================  =================================================================

Two functions are left to numpy because numba's libm does not give numpy's bits: the
bearing's ``arctan2`` (numpy's SIMD loop) and the ``gaussian`` profile's ``exp``. The random
draws stay numpy's ``Generator`` streams, per trial, in the same order.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.kernels_math import jit, wrap
from resloc.world.zones import RiskProfile

__all__ = [
    "PROFILE_CODE",
    "ZoneArrays",
    "move_team",
    "noisy_measurements",
    "team_links",
    "zone_arrays",
    "zone_risk",
]

#: The compiled risk profiles (``gaussian``'s ``exp`` stays numpy's).
PROFILE_CODE = {
    RiskProfile.LINEAR: 0,
    RiskProfile.QUADRATIC: 1,
    RiskProfile.STAIRCASE: 2,
    RiskProfile.CONSTANT: 3,
}


@jit
def move_team(pose, leader, offsets, projection, gain, v_max, omega_max, dt, u, new_pose):
    """The true commands and the move of every robot, in place.

    Parameters
    ----------
    pose : ndarray, shape (B, 3)
        Poses at step ``k``.
    leader : ndarray, shape (2,)
        The leader's desired position at step ``k + 1``.
    offsets : ndarray, shape (N - 1, 2)
        The followers' offsets from it (in the world frame): robot ``b`` of a team of ``N``
        goes to ``leader`` (``b % N == 0``) or ``leader + offsets[b % N - 1]``.
    projection, gain, v_max, omega_max, dt : float
    u : ndarray, shape (B, 2)
        Out: the commands ``(v, omega)``.
    new_pose : ndarray, shape (B, 3)
        Out: the poses at step ``k + 1``.
    """
    n = offsets.shape[0] + 1
    for b in range(pose.shape[0]):
        x, y, th = pose[b, 0], pose[b, 1], pose[b, 2]
        r = b % n
        want_x = leader[0] if r == 0 else leader[0] + offsets[r - 1, 0]
        want_y = leader[1] if r == 0 else leader[1] + offsets[r - 1, 1]
        c, s = math.cos(th), math.sin(th)
        vx = gain * (want_x - (x + projection * c))
        vy = gain * (want_y - (y + projection * s))
        speed = math.sqrt(vx * vx + vy * vy)
        scale = min(1.0, v_max / max(speed, 1e-12))
        vx *= scale
        vy *= scale
        v = c * vx + s * vy
        w = (-s * vx + c * vy) / projection
        v = min(max(v, -v_max), v_max)
        w = min(max(w, -omega_max), omega_max)
        u[b, 0] = v
        u[b, 1] = w
        new_pose[b, 0] = x + v * c * dt
        new_pose[b, 1] = y + v * s * dt
        new_pose[b, 2] = wrap(th + w * dt)


@jit
def _count_team_links(q, n, r2):
    count = 0
    for first in range(0, q.shape[0], n):
        for a in range(first, first + n):
            for b in range(first, first + n):
                dx = q[b, 0] - q[a, 0]
                dy = q[b, 1] - q[a, 1]
                if a != b and dx * dx + dy * dy <= r2:
                    count += 1
    return count


@jit
def _fill_team_links(pose, q, n, r2, comm_radius, i, j, dx, dy, rng, in_comm, counts):
    e = 0
    for first in range(0, q.shape[0], n):
        for a in range(first, first + n):
            for b in range(first, first + n):
                sx = q[b, 0] - q[a, 0]
                sy = q[b, 1] - q[a, 1]
                if a == b or not sx * sx + sy * sy <= r2:
                    continue
                i[e] = a
                j[e] = b
                ex = pose[b, 0] - pose[a, 0]
                ey = pose[b, 1] - pose[a, 1]
                dx[e] = ex
                dy[e] = ey
                rng[e] = math.hypot(ex, ey)  # |p_i - p_j| too: hypot ignores signs
                in_comm[e] = rng[e] <= comm_radius
                counts[first // n] += 1
                e += 1


@jit
def _shifted(pose, n, radius):
    """``radius_links``' search coordinates: team ``t`` moved ``t * span`` along ``x``."""
    B = pose.shape[0]
    lo, hi = pose[0, 0], pose[0, 0]
    for b in range(1, B):
        lo = min(lo, pose[b, 0])
        hi = max(hi, pose[b, 0])
    span = (hi - lo) + 4.0 * radius + 1.0
    q = np.empty((B, 2))
    for b in range(B):
        q[b, 0] = pose[b, 0] + float(b // n) * span
        q[b, 1] = pose[b, 1]
    return q


@jit
def team_links(pose, n, radius, comm_radius):
    """The sensed links of teams of ``n`` consecutive robots, and what the world needs of
    them: twin of ``radius_links(pose[:, :2], team, radius, method="pairs")`` (the same
    search coordinates and test, so the same links in the same order) and of the ranges
    and radio test the world computes from them.

    Parameters
    ----------
    pose : ndarray, shape (B, 3), ``B`` a multiple of ``n``
    n : int
        Robots per team.
    radius, comm_radius : float

    Returns
    -------
    i, j : ndarray of int64, shape (E,)
        Sorted by ``i`` then ``j``.
    dx, dy : ndarray, shape (E,)
        ``p_j - p_i``.
    rng : ndarray, shape (E,)
        ``hypot(dx, dy)``.
    in_comm : ndarray of bool, shape (E,)
        ``rng <= comm_radius``.
    counts : ndarray of int64, shape (B // n,)
        Links per team.
    """
    q = _shifted(pose, n, radius)
    E = _count_team_links(q, n, radius * radius)
    i, j = np.empty(E, np.int64), np.empty(E, np.int64)
    dx, dy, rng = np.empty(E), np.empty(E), np.empty(E)
    in_comm = np.empty(E, np.bool_)
    counts = np.zeros(pose.shape[0] // n, np.int64)
    _fill_team_links(pose, q, n, radius * radius, comm_radius, i, j, dx, dy, rng, in_comm, counts)
    return i, j, dx, dy, rng, in_comm, counts


@jit
def noisy_measurements(rng, angle, pose, i, noise, std):
    """Measured range and bearing of every link: twin of ``range_bearing`` (its bearing's
    ``arctan2`` given as ``angle``) plus ``noise * std``, the range's absolute value and the
    bearing wrapped.

    Parameters
    ----------
    rng, angle : ndarray, shape (E,)
        ``hypot(dx, dy)`` and ``arctan2(dy, dx)`` of ``p_j - p_i``.
    pose : ndarray, shape (B, 3)
    i : ndarray of int64, shape (E,)
        Observers.
    noise : ndarray, shape (E, 2)
        Standard normal draws.
    std : ndarray, shape (2,)

    Returns
    -------
    ndarray, shape (E, 2)
    """
    E = rng.shape[0]
    z = np.empty((E, 2))
    for e in range(E):
        z[e, 0] = abs(rng[e] + noise[e, 0] * std[0])
        z[e, 1] = wrap(wrap(angle[e] - pose[i[e], 2]) + noise[e, 1] * std[1])
    return z


@jit
def zone_risk(p, centre, radius, peak, profile, tau):
    """Combined risk ``1 - prod_z (1 - R_z(p))`` at positions ``p: (B, 2)``: twin of
    :meth:`ZoneField.risk <resloc.world.zones.ZoneField.risk>` for zones given as arrays
    (:func:`zone_arrays`; ``profile`` codes of :data:`PROFILE_CODE`). Returns ``(B,)``."""
    B = p.shape[0]
    out = np.empty(B)
    for b in range(B):
        safe = 1.0
        for k in range(centre.shape[0]):
            s = math.hypot(p[b, 0] - centre[k, 0], p[b, 1] - centre[k, 1]) / radius[k]
            code = profile[k]
            if code == 0:
                g = 1.0 - s
            elif code == 1:
                g = 1.0 - s * s
            elif code == 2:
                g = 1.0 - 0.2 * math.floor(min(s, 0.999999) * 5.0)
            else:
                g = 1.0
            unit = min(max(g, 0.0), 1.0) if s <= 1.0 else 0.0
            r = peak[k] * unit
            if not r >= tau[k]:
                r = 0.0
            safe *= 1.0 - r
        out[b] = 1.0 - safe
    return out


class ZoneArrays:
    """A zone field as :func:`zone_risk` takes it (centres ``(Z, 2)``, radii, peaks,
    profile codes and thresholds ``(Z,)``)."""

    def __init__(self, zones) -> None:
        self.centre = np.array([z.center for z in zones], float).reshape(-1, 2)
        self.radius = np.array([z.radius for z in zones], float)
        self.peak = np.array([z.peak for z in zones], float)
        self.profile = np.array([PROFILE_CODE[z.profile] for z in zones], np.int64)
        self.tau = np.array([z.tau for z in zones], float)

    def risk(self, p: np.ndarray) -> np.ndarray:
        """``R(p)`` at positions ``p: (B, 2)``, shape (B,)."""
        return zone_risk(p, self.centre, self.radius, self.peak, self.profile, self.tau)


def zone_arrays(field) -> ZoneArrays | None:
    """The compiled form of a :class:`~resloc.world.zones.ZoneField`, or None when a zone's
    profile has no compiled twin (``gaussian``) or the field is empty."""
    zones = field.zones
    if not zones or any(z.profile not in PROFILE_CODE for z in zones):
        return None
    return ZoneArrays(zones)


_WARM: list[bool] = []


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the world's kernels on a tiny world,
    outside any timed section; once per process."""
    if _WARM:
        return
    _WARM.append(True)
    pose = np.array([[0.0, 0.0, 0.1], [0.5, 0.2, -0.3]])
    u, moved = np.empty((2, 2)), np.empty((2, 3))
    move_team(pose, np.zeros(2), np.array([[-0.5, 0.0]]), 0.05, 1.0, 0.2, 3.0, 0.03, u, moved)
    i, _, dx, dy, distance, _, _ = team_links(pose, 2, 1.0, 1.0)
    noisy_measurements(distance, np.arctan2(dy, dx), pose, i, np.zeros((len(i), 2)), np.ones(2))
    zones = ZoneArrays([])
    zone_risk(pose[:, :2], zones.centre, zones.radius, zones.peak, zones.profile, zones.tau)
