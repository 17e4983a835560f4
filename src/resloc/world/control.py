"""Leader path and leader-follower formation control (the true robots' commands)."""

from __future__ import annotations

import bisect

import numpy as np

from resloc.errors import ConfigError

__all__ = ["LeaderPath", "lattice_offsets", "si_to_unicycle"]


class LeaderPath:
    """A path of straight segments and left half-circle arcs, followed at constant speed.

    Parameters
    ----------
    waypoints : list
        ``[x, y]`` points; the string ``"arc"`` between two points makes a half-circle
        (turning left) whose diameter joins them.
    """

    def __init__(self, waypoints: list) -> None:
        pts: list[np.ndarray] = []
        kinds: list[str] = []
        pending_arc = False
        for k, w in enumerate(waypoints):
            if isinstance(w, str):
                if w != "arc" or not pts or pending_arc:
                    raise ConfigError(
                        f"motion.waypoints[{k}]: {w!r} must be 'arc' between two [x, y] points"
                    )
                pending_arc = True
                continue
            p = np.asarray(w, dtype=float)
            if p.shape != (2,) or not np.all(np.isfinite(p)):
                raise ConfigError(f"motion.waypoints[{k}]: expected [x, y], got {w!r}")
            if pts:
                kinds.append("arc" if pending_arc else "line")
            pending_arc = False
            pts.append(p)
        if pending_arc or len(pts) < 2:
            raise ConfigError("motion.waypoints: need at least two [x, y] points, 'arc' between")
        self.points = np.array(pts)
        self.kinds = kinds
        lengths = []
        for a, b, kind in zip(self.points[:-1], self.points[1:], kinds, strict=True):
            d = float(np.linalg.norm(b - a))
            lengths.append(np.pi * d / 2.0 if kind == "arc" else d)
        self.lengths = np.array(lengths)
        self.cumulative = np.concatenate([[0.0], np.cumsum(self.lengths)])
        # What at() needs of each segment, computed once (the same expressions, so the
        # same values): its start, direction and heading (line), centre, radius, start angle
        # (arc).
        self._segments = [self._segment(k) for k in range(len(kinds))]
        self._last = len(kinds) - 1
        self._cumulative = [float(c) for c in self.cumulative]
        self._lengths = [max(float(v), 1e-12) for v in self.lengths]

    def _segment(self, k: int) -> tuple:
        a, b = self.points[k], self.points[k + 1]
        if self.kinds[k] == "line":
            d = b - a
            return ("line", a, d, float(np.arctan2(d[1], d[0])))
        centre = 0.5 * (a + b)
        r = 0.5 * float(np.linalg.norm(b - a))
        phi0 = float(np.arctan2(a[1] - centre[1], a[0] - centre[0]))
        return ("arc", centre, r, phi0)

    @property
    def length(self) -> float:
        """Total path length (m)."""
        return float(self.cumulative[-1])

    def at(self, s: float) -> tuple[np.ndarray, float]:
        """Position and heading at arc length ``s`` (clamped to the path).

        Returns
        -------
        p : ndarray, shape (2,)
        heading : float
        """
        s = float(s)
        s = min(max(s, 0.0), self._cumulative[-1]) if s == s else s  # clamp (nan stays nan)
        k = min(bisect.bisect_right(self._cumulative, s) - 1, self._last)
        t = (s - self._cumulative[k]) / self._lengths[k]
        kind, origin, size, angle = self._segments[k]
        if kind == "line":
            return origin + t * size, angle
        phi = angle + np.pi * t  # counter-clockwise (left turn)
        p = origin + size * np.array([np.cos(phi), np.sin(phi)])
        return p, phi + np.pi / 2.0


def lattice_offsets(n_followers: int, spacing: float, gap: float) -> np.ndarray:
    """Formation offsets of followers on a square lattice behind (``-x`` of) the leader.

    ``ceil(sqrt(n))`` rows, centred on the leader's line; 16 followers give the paper's
    4 x 4 lattice.

    Returns
    -------
    ndarray, shape (n_followers, 2)
    """
    if n_followers == 0:
        return np.zeros((0, 2))
    side = int(np.ceil(np.sqrt(n_followers)))
    k = np.arange(n_followers)
    col = k // side
    row = k % side
    x = -(gap + col * spacing)
    y = (row - (side - 1) / 2.0) * spacing
    return np.stack([x, y], axis=1)


def si_to_unicycle(
    pose: np.ndarray, v_si: np.ndarray, projection: float, v_max: float, omega_max: float
) -> np.ndarray:
    """Map single-integrator velocities to unicycle commands (Robotarium's near-identity
    diffeomorphism) and saturate them.

    Parameters
    ----------
    pose : ndarray, shape (B, 3)
    v_si : ndarray, shape (B, 2)
        Desired planar velocities of the point ``projection`` ahead of each robot.
    projection, v_max, omega_max : float

    Returns
    -------
    ndarray, shape (B, 2)
        ``(v, omega)`` with ``|v| <= v_max`` and ``|omega| <= omega_max``.
    """
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    v = c * v_si[:, 0] + s * v_si[:, 1]
    w = (-s * v_si[:, 0] + c * v_si[:, 1]) / projection
    return np.stack([np.clip(v, -v_max, v_max), np.clip(w, -omega_max, omega_max)], axis=1)
