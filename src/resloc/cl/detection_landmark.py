"""Zone landmarks: no robot fuses a neighbour whose broadcast position is inside the map.

With zone trust (:mod:`resloc.cl.detection_zone`) a robot inside a mapped sensing danger
zone fuses none of its own readings: its estimate is dead reckoning plus the position fixes
its outside partners send it, i.e. it is built from those partners' estimates. When the
partners then fuse that robot as a landmark they fuse their own information back (a loop
naive fusion does not model), and a *compromised* robot inside the zone closes the loop
with a lie: it is told where it is by its victims, whom it has pulled along with its last
lie, and lies again on top of that (``docs/attack/compromised_long.md``: over the default
1000 steps this loop, while compromised robots are inside the map, is where their harm
grows from x2 to x7-x60). This stage withholds, from every other stage as zone trust does,
each link ``(i, j)`` whose neighbour's broadcast position lies inside the map grown by
``zone_landmarks_margin``:

``withhold_ij  <=>  min_z ( ||p_j - c_z|| - r_z - margin ) <= 0``

A robot inside the map still fuses its partners' fixes (zone trust's substitution); it is
only not used as a landmark by others until it leaves. A policy on the message, not an
inconsistency verdict: it reads only the broadcast position and the map, whatever the
reading or the claimed covariance say.

What it assumes, where it fails:

* The map (as zone trust). Without an SDZ nothing is withheld (the clean run is unchanged).
* The broadcast position is the neighbour's claim. A compromised robot inside the map can
  move its claim out of it only by a lie at least as large as its distance to the map's
  edge plus the margin, which the other stages judge as any other lie. (In the simulator
  a compromised robot's lie is carried as the equivalent reading, so its broadcast
  position field is its honest estimate: the claim's move out of the map is not modelled;
  the margin is there so that the lies the gates accept, tens of millimetres, could not
  carry it out.)
* Honest robots inside the map stop being landmarks: their neighbours lose those links
  while they are inside (measured as the map's price, the run with nothing attacked).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_zone import inside_zone_map
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["ZoneLandmarks"]


class ZoneLandmarks:
    """Withhold the links whose neighbour's broadcast position lies inside the landmark map
    (``params.zone_landmarks_map``: the SDZ map grown by the margin).

    Needs the neighbours' broadcast estimates (``Evidence.x_nb``); without them it raises
    (an attacker's copy of the detector must be given them, or it would believe the
    withheld rows accepted).
    """

    name: ClassVar[str] = "zone_landmarks"
    compiled: ClassVar[bool] = False
    overrides: ClassVar[bool] = False
    #: Its rows are withheld from every other stage (:func:`resloc.cl.detection.detect`).
    withholds: ClassVar[bool] = True

    def active(self, params: CLParams) -> bool:
        return bool(params.zone_landmarks)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if evidence.x_nb is None:
            raise ValueError(
                "detector.zone_landmarks needs the neighbours' broadcast estimates "
                "(Evidence.x_nb); an attacker's oracle gets them from fix_context"
            )
        return inside_zone_map(np.asarray(evidence.x_nb)[:, :2], params.zone_landmarks_map)


def not_landmarks(
    params: CLParams, x_nb: np.ndarray, held: np.ndarray | None = None
) -> np.ndarray | None:
    """``held`` (links already out of the redundancy stage's references, or None) with the
    links this stage withholds added: a withheld neighbour's fix enters no reference of
    the redundancy stage either (its lie would otherwise still pull the observer's other
    fixes' references). None when neither applies.

    Parameters
    ----------
    params : CLParams
    x_nb : ndarray, shape (E, 3)
        The neighbours' broadcast estimates.
    held : ndarray of bool, shape (E,), optional
    """
    if not params.zone_landmarks:
        return held
    out = inside_zone_map(np.asarray(x_nb)[:, :2], params.zone_landmarks_map)
    return out if held is None else held | out
