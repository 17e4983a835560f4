"""TUM trajectories for evo: ``t x y z qx qy qz qw`` (w last), one file per robot and source.

Layout of the ``tum/`` directory::

    robot1.groundtruth.txt      true poses (only where the truth exists)
    robot1.ckf.txt              estimates, every step
    team_aligned/robot1.ckf.txt estimates moved by ONE SE(2) transform fitted over the team
    alignment.csv               position RMSE per estimator and robot: raw, team, per robot

``evo_ape tum tum/robot1.groundtruth.txt tum/robot1.ckf.txt -a`` aligns each robot on its
own (it hides errors between robots); ``evo_ape tum tum/robot1.groundtruth.txt
tum/team_aligned/robot1.ckf.txt`` (no ``-a``) gives the team-aligned error, the meaningful
one when the robots measure only each other (``docs/export.md``).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from resloc.export.geometry import aligned_errors, yaw_quaternion

__all__ = ["read_tum", "tum_lines", "write"]


def tum_lines(stamps: np.ndarray, poses: np.ndarray) -> str:
    """TUM text of planar poses.

    Parameters
    ----------
    stamps : ndarray, shape (K,)
        Seconds.
    poses : ndarray, shape (K, 3)
        ``(x, y, theta)``; ``z = 0``.
    """
    q = yaw_quaternion(poses[:, 2])
    table = np.column_stack([stamps, poses[:, 0], poses[:, 1], np.zeros(len(poses)), q])
    rows = [
        f"{t:.6f} {x:.6f} {y:.6f} {z:.1f} {qx:.1f} {qy:.1f} {qz:.9f} {qw:.9f}"
        for t, x, y, z, qx, qy, qz, qw in table
    ]
    return "".join(r + "\n" for r in rows)


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (K,) and planar poses (K, 3) of a TUM file written by :func:`tum_lines`."""
    table = np.loadtxt(path, ndmin=2)
    theta = 2.0 * np.arctan2(table[:, 6], table[:, 7])
    return table[:, 0], np.column_stack([table[:, 1], table[:, 2], np.angle(np.exp(1j * theta))])


def write(rec, target: Path, options) -> dict:
    """Write the ``tum/`` directory of ``rec`` at ``target``; return the alignment table.

    Returns
    -------
    dict
        ``{estimator: {"raw" | "team" | "per_robot": rmse, "robots": {...}}}`` (m).
    """
    target = Path(target)
    (target / "team_aligned").mkdir(parents=True)
    stamps = rec.t0 + rec.time
    for r, robot in enumerate(rec.robots):
        ok = rec.valid[:, r]
        (target / f"{robot}.groundtruth.txt").write_text(
            tum_lines(stamps[ok], rec.truth[ok, r]), encoding="utf-8"
        )
    info: dict = {}
    rows = []
    for name, track in rec.estimates.items():
        finite = np.isfinite(track).all(-1)
        err = aligned_errors(rec.truth, track, rec.valid & finite)
        tx, ty, angle = err.team_transform
        c, s = np.cos(angle), np.sin(angle)
        moved = track.copy()
        moved[..., 0] = c * track[..., 0] - s * track[..., 1] + tx
        moved[..., 1] = s * track[..., 0] + c * track[..., 1] + ty
        moved[..., 2] = np.angle(np.exp(1j * (track[..., 2] + angle)))
        for r, robot in enumerate(rec.robots):
            ok = finite[:, r]
            (target / f"{robot}.{name}.txt").write_text(
                tum_lines(stamps[ok], track[ok, r]), encoding="utf-8"
            )
            (target / "team_aligned" / f"{robot}.{name}.txt").write_text(
                tum_lines(stamps[ok], moved[ok, r]), encoding="utf-8"
            )
            rows.append([name, robot, err.raw[r], err.team[r], err.per_robot[r]])
        info[name] = {
            **err.overall(),
            "team_transform": {"tx": tx, "ty": ty, "angle_rad": angle},
            "robots": {
                robot: {"raw": err.raw[r], "team": err.team[r], "per_robot": err.per_robot[r]}
                for r, robot in enumerate(rec.robots)
            },
        }
        rows.append([name, "all", *(info[name][k] for k in ("raw", "team", "per_robot"))])
    with (target / "alignment.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["estimator", "robot", "rmse_raw_m", "rmse_team_aligned_m", "rmse_per_robot_m"])
        w.writerows([*row[:2], *(f"{v:.6g}" for v in row[2:])] for row in rows)
    return info
