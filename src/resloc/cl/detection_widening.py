"""What the stages that scale a robot's own covariance before the correction share.

:mod:`resloc.cl.detection_outvoted` (widening on its observers' notes) and
:mod:`resloc.cl.detection_startup` (a floor in the first corrections) both multiply whole
``3 x 3`` blocks of ``P (B, 3, 3)`` by a per-robot factor and keep that factor in their
per-robot store (keyed ``(j, j)``, column 1), where a full-knowledge attacker reads it.
"""

from __future__ import annotations

import numpy as np

from resloc.cl.memory import LinkMemory

__all__ = ["applied_stage_factors", "floor_factors", "keep_exempt", "scale_robots"]


def floor_factors(P: np.ndarray, floor) -> np.ndarray:
    """The factor ``(K,)`` that raises each block of ``P (K, 3, 3)`` to a position
    standard deviation of ``floor`` (m; a scalar or ``(K,)``):
    ``max(floor^2 / max(P_xx, P_yy), 1)`` (1 where the larger diagonal entry is already
    above it; a nan entry gives nan, as ``np.maximum`` does)."""
    P = np.asarray(P, float)
    largest = np.maximum(P[:, 0, 0], P[:, 1, 1])
    return np.maximum(np.asarray(floor, float) ** 2 / largest, 1.0)


def scale_robots(P: np.ndarray, robots: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``P (B, 3, 3)`` with robot ``robots[k]``'s block times ``factor[k]`` where it is
    above 1; ``P`` itself (not a copy) when no factor is."""
    raised = factor > 1.0
    if not raised.any():
        return P
    P = np.array(P, float)
    P[robots[raised]] *= factor[raised, None, None]
    return P


def keep_exempt(P: np.ndarray, P_before: np.ndarray, exempt: np.ndarray | None) -> np.ndarray:
    """``P (B, 3, 3)``, the covariances after the stages, with the ``exempt (B,)`` robots'
    blocks as they were before them (``P_before``); ``P`` itself when none differs.

    Simulation only: a compromised robot runs its own software, and a stage that widens
    its own covariance would widen what it claims and weaken its lies; the attacker marks
    its robots (``LinkMemory.exempt``) and they skip every such stage. The stages' stores
    still hold the factor they computed for them: read them through
    :func:`applied_stage_factors` with the same mask."""
    if exempt is None or P is P_before:
        return P
    rows = np.flatnonzero(exempt)
    if not rows.size or np.array_equal(P[rows], P_before[rows]):
        return P
    P = np.array(P, float)
    P[rows] = P_before[rows]
    return P


def applied_stage_factors(memory: LinkMemory, stage: str, B: int) -> np.ndarray:
    """The factor ``(B,)`` each robot's covariance was scaled by in its last correction by
    the stage whose store is ``stage`` (1: none)."""
    state = memory.stage_statistic(stage, width=2)
    robots = np.arange(B)
    f = state.get(robots, robots)[:, 1]
    return np.where(f > 1.0, f, 1.0)
