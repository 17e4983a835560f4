"""MRCLAM over the wire: the recorded dataset replaces the simulated world.

The world process loads the dataset and cuts it into steps with the code of ``resloc mrclam``
(:func:`~resloc.datasets.mrclam.load_mrclam`, :func:`~resloc.experiments.mrclam.prepare_replay`)
and publishes each step's odometry and robot-to-robot range/bearing sightings to the robot
processes; the recorder scores the robots' reported estimates against the motion-capture
ground truth with the same scoring and writer (``score_estimate``, ``save_mrclam``).
Landmark sightings are not replayed: they are absolute fixes, not robot-to-robot links
(``resloc mrclam --no-landmarks`` is the in-process equivalent).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from resloc.runtime.team import TeamSetup
from resloc.world.world import WorldStep

__all__ = ["ReplaySource", "load_replay", "replay_link_params", "score_replay"]


@functools.lru_cache(maxsize=2)
def _load(path: str, duration: float | None, config) -> object:
    from resloc.datasets.mrclam import load_mrclam
    from resloc.experiments.mrclam import prepare_replay

    return prepare_replay(load_mrclam(path, duration=duration), config)


def load_replay(path: str | Path, team: TeamSetup):
    """The :class:`~resloc.experiments.mrclam.Replay` of ``path`` under the team's config."""
    cfg = team.mrclam
    return _load(str(path), cfg.duration, cfg)


def replay_link_params(team: TeamSetup, z: np.ndarray) -> list[tuple[np.ndarray, object]]:
    """Rows of ``z: (E, 2)`` grouped by range-noise level with each level's parameters,
    as ``resloc mrclam`` fuses them (the range noise grows with the range)."""
    from resloc.experiments.mrclam import level_groups, range_noise_level

    return level_groups(range_noise_level(z[:, 0], team.mrclam), team.params, {})


class ReplaySource:
    """Steps of a recorded dataset as :class:`WorldStep` (robot-to-robot sightings only)."""

    def __init__(self, path: Path, team: TeamSetup) -> None:
        self.rp = load_replay(path, team)
        self.cfg = team.mrclam
        self.n = self.rp.dataset.n_robots
        self.steps = self.rp.steps
        self.seed = self.cfg.seed
        self.dt = self.cfg.dt
        self.k = 0

    def initial_estimates(self) -> tuple[np.ndarray, np.ndarray]:
        """Ground truth at t = 0 with ``init_std`` (as ``resloc mrclam``)."""
        return self.rp.initial_estimates(self.cfg.init_std)

    def initial_pose(self) -> np.ndarray:
        return self.rp.truth[0].copy()

    def true_pose(self, b: int) -> np.ndarray:
        return self.rp.truth[self.k, b].copy()

    def step(self) -> WorldStep:
        rp = self.rp
        self.k += 1
        k = self.k
        rows = np.arange(rp.bounds[k], rp.bounds[k + 1])
        rows = rows[rp.is_robot[rows]]
        return WorldStep(
            k,
            rp.truth[k].copy(),
            rp.u[k - 1].copy(),
            rp.obs[rows],
            rp.target[rows],
            rp.z[rows],
            rp.attacked[rows],
            rp.channel_ok[rows],
            rp.risk_s[k],
            rp.risk_c[k],
            np.full(self.n, float(self.n)),  # as resloc mrclam: the team is connected
        )


def score_replay(team: TeamSetup, path: str, X, P, reports: dict, steps: int, wall: float):
    """The :class:`~resloc.experiments.mrclam.MRCLAMResult` of the robots' reports.

    Parameters
    ----------
    X, P : ndarray, shapes (K + 1, N, 3), (K + 1, N, 3, 3)
        Reported estimates and covariances per step (carried forward where missing).
    reports : dict
        ``reports[k][robot]``: the REPORT bodies.
    steps : int
        Steps completed (the result covers steps ``0 .. steps``).
    """
    from resloc.experiments.mrclam import empty_link_log, replay_result, score_estimate
    from resloc.runtime.messages import FLAG_DELIVERED, FLAG_DETECTED, FLAG_FUSED, FLAG_TRIGGERED

    flags = {
        "detected": FLAG_DETECTED,
        "triggered": FLAG_TRIGGERED,
        "delivered": FLAG_DELIVERED,
        "fused": FLAG_FUSED,
    }

    K = steps
    rp = load_replay(path, team).head(K)
    M = len(rp.step)
    links = empty_link_log(M)
    for k in range(1, K + 1):
        rows = np.arange(rp.bounds[k], min(rp.bounds[k + 1], M))
        rows = rows[rp.is_robot[rows]]
        for r, rep in reports.get(k, {}).items():
            mine = rows[rp.obs[rows] == r]
            if len(mine) != len(rep["flags"]):
                continue
            links["norm"][mine] = rep["norm"]
            for name, bit in flags.items():
                links[name][mine] = (rep["flags"] & bit) > 0
    name = team.filter_name
    est = score_estimate(name, rp, X, P, links, wall)
    info = {"runtime": "resloc swarm --replay (robot processes over Zenoh)"}
    return replay_result(rp, team.mrclam, {name: est}, wall, info)
