"""Measurement attackers: biases, schedules, trigger attacks, gauge-aimed and coordinated lies.

Each one falsifies the links it controls with the largest fraction of its lie that the victim
accepts (:class:`~resloc.world.attackers.base.SensingLie`): a bias sits at the detector's
acceptance limit per measurement and, through the sequence tests' state, in sum over their
windows; when a CUSUM's statistic has room (``h`` minus its current value) the first
measurements spend it at once (a burst), then the lie stays at what the reference ``k``
admits.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from resloc.angles import wrap_angle
from resloc.models.measurement import range_bearing
from resloc.world.attackers.base import SensingLie

__all__ = [
    "BearingBias",
    "CommonTranslation",
    "CoordinatedDisplacement",
    "ForceTrigger",
    "OnOffBias",
    "RampBias",
    "RangeBias",
    "ReviewerGateOnly",
    "StarveTrigger",
    "measurement_difference",
]

#: Largest injection searched: range (m), bearing (rad). The detector is what limits each
#: lie (the acceptance oracle takes the largest accepted fraction of it); the sizes only
#: bound the search and are themselves searched where they could matter.
MAX_RANGE_LIE = 2.0
MAX_BEARING_LIE = 1.5


class RangeBias(SensingLie):
    name: ClassVar[str] = "range_bias"
    template: ClassVar[str] = (
        "persistent +range bias on every SDZ link, as large as the victim's whole detector "
        "(gate and sequence tests, their current state) accepts, up to {size:g} m"
    )
    defaults: ClassVar[dict] = {"size": MAX_RANGE_LIE}
    grid: ClassVar[tuple] = ({"size": 0.5}, {"size": MAX_RANGE_LIE})

    def lie(self, rows, z, z_hat, step):
        return np.broadcast_to([self.size, 0.0], (len(rows), 2)).copy()


class BearingBias(SensingLie):
    name: ClassVar[str] = "rotation"
    template: ClassVar[str] = (
        "a common rotation of what every SDZ sensor reports (+bearing bias, same sign on "
        "every link), at the acceptance limit, up to {size:g} rad"
    )
    defaults: ClassVar[dict] = {"size": MAX_BEARING_LIE}
    grid: ClassVar[tuple] = ({},)

    def lie(self, rows, z, z_hat, step):
        return np.broadcast_to([0.0, self.size], (len(rows), 2)).copy()


class CommonTranslation(SensingLie):
    name: ClassVar[str] = "translation"
    template: ClassVar[str] = (
        "a common translation of what every SDZ sensor reports: each neighbour seen up to "
        "{size:g} m further east (world frame), at the acceptance limit"
    )
    defaults: ClassVar[dict] = {"size": MAX_RANGE_LIE}
    grid: ClassVar[tuple] = ({},)

    def lie(self, rows, z, z_hat, step):
        xi, xj = step.pose[step.i[rows]], step.pose[step.j[rows]].copy()
        moved = xj.copy()
        moved[:, 0] += self.size
        return measurement_difference(range_bearing(xi, moved), range_bearing(xi, xj))


class OnOffBias(RangeBias):
    name: ClassVar[str] = "on_off"
    template: ClassVar[str] = (
        "the range bias (up to {size:g} m) switched on for {period:g} steps and off for as "
        "long: every on-phase spends the sequence tests' recovered slack in a burst"
    )
    defaults: ClassVar[dict] = {"size": MAX_RANGE_LIE, "period": 60}
    grid: ClassVar[tuple] = ({"period": 10}, {"period": 60})

    def ceiling(self, step):
        return float((step.k // self.period) % 2 == 0)


class RampBias(RangeBias):
    name: ClassVar[str] = "ramp"
    template: ClassVar[str] = (
        "a range bias ramping from 0 to {size:g} m over {ramp_s:g} s (a slow drift), at most "
        "what the detector accepts"
    )
    defaults: ClassVar[dict] = {"size": MAX_RANGE_LIE, "ramp_s": 10.0}
    grid: ClassVar[tuple] = ({"ramp_s": 2.0}, {"ramp_s": 10.0})

    def ceiling(self, step):
        return min(1.0, step.k * step.dt / self.ramp_s)


class StarveTrigger(SensingLie):
    name: ClassVar[str] = "starve"
    template: ClassVar[str] = (
        "trigger starvation: measurements moved onto the victim's prediction (innovation "
        "toward 0), so the event trigger never fires and nothing is fused"
    )

    def lie(self, rows, z, z_hat, step):
        return measurement_difference(z_hat, z)


class ForceTrigger(SensingLie):
    name: ClassVar[str] = "force"
    template: ClassVar[str] = (
        "trigger forcing: the largest accepted innovation (up to {size:g} m and rad), sign "
        "alternating every step (range and bearing), so every link transmits and fuses noise"
    )
    defaults: ClassVar[dict] = {"size": MAX_BEARING_LIE}

    def lie(self, rows, z, z_hat, step):
        sign = self.size if step.k % 2 else -self.size
        return np.broadcast_to([sign, sign], (len(rows), 2)).copy()


class ReviewerGateOnly(RangeBias):
    name: ClassVar[str] = "reviewer"
    template: ClassVar[str] = (
        "the outside reviewer's attacker: the range bias (up to {size:g} m) kept under the "
        "victim's gate only (knows nothing of the sequence tests)"
    )
    gate_only: ClassVar[bool] = True
    grid: ClassVar[tuple] = ({},)


class CoordinatedDisplacement(SensingLie):
    name: ClassVar[str] = "displaced"
    template: ClassVar[str] = (
        "coordinated lies on every link of robot {target:g} (it sees and is seen as if it "
        "stood elsewhere): a displacement to its left ramping at {speed:g} m/s to {size:g} m, "
        "anywhere in the arena, at the acceptance limit"
    )
    defaults: ClassVar[dict] = {"target": 5, "speed": 0.05, "size": MAX_RANGE_LIE}
    grid: ClassVar[tuple] = ({"speed": 0.05}, {"speed": 0.5})

    def mark(self, sdz_attacked, step):
        rid_i, rid_j = step.i % step.robots, step.j % step.robots
        return (rid_i == self.target) | (rid_j == self.target)

    def lie(self, rows, z, z_hat, step):
        offset = min(self.size, self.speed * step.k * step.dt)
        xi, xj = step.pose[step.i[rows]].copy(), step.pose[step.j[rows]].copy()
        true = range_bearing(xi, xj)
        for x in (xi, xj):
            me = (step.i[rows] if x is xi else step.j[rows]) % step.robots == self.target
            # sideways: to the target's left, so its neighbours' ranges change little
            x[me, 0] -= offset * np.sin(x[me, 2])
            x[me, 1] += offset * np.cos(x[me, 2])
        return measurement_difference(range_bearing(xi, xj), true)


def measurement_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a - b`` for range/bearing rows, bearing wrapped, shape (n, 2)."""
    d = np.asarray(a, float) - np.asarray(b, float)
    d[:, 1] = wrap_angle(d[:, 1])
    return d
