"""What the stages that scale a robot's own covariance before the correction share.

:mod:`resloc.cl.detection_outvoted` (widening on its observers' notes) and
:mod:`resloc.cl.detection_startup` (a floor in the first corrections) both multiply whole
``3 x 3`` blocks of ``P (B, 3, 3)`` by a per-robot factor and keep that factor in their
per-robot store (keyed ``(j, j)``, column 1), where a full-knowledge attacker reads it.
"""

from __future__ import annotations

import numpy as np

from resloc.cl.memory import LinkMemory

__all__ = ["applied_stage_factors", "scale_robots"]


def scale_robots(P: np.ndarray, robots: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``P (B, 3, 3)`` with robot ``robots[k]``'s block times ``factor[k]`` where it is
    above 1; ``P`` itself (not a copy) when no factor is."""
    raised = factor > 1.0
    if not raised.any():
        return P
    P = np.array(P, float)
    P[robots[raised]] *= factor[raised, None, None]
    return P


def applied_stage_factors(memory: LinkMemory, stage: str, B: int) -> np.ndarray:
    """The factor ``(B,)`` each robot's covariance was scaled by in its last correction by
    the stage whose store is ``stage`` (1: none)."""
    state = memory.stage_statistic(stage, width=2)
    robots = np.arange(B)
    f = state.get(robots, robots)[:, 1]
    return np.where(f > 1.0, f, 1.0)
