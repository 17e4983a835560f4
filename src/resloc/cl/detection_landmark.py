"""Zone landmarks: a neighbour inside the mapped danger zone is a weak landmark.

With zone trust (:mod:`resloc.cl.detection_zone`) a robot inside a mapped sensing danger
zone fuses none of its own readings: its estimate is dead reckoning plus the position fixes
its outside partners send it, i.e. it is built from those partners' estimates. When the
partners then fuse that robot as a landmark they fuse their own information back (a loop
naive fusion does not model), and a *compromised* robot inside the zone closes the loop
with a lie: it is told where it is by its victims, whom its last lie pulled, and lies again
on top of that. Over the default 1000 steps this loop, while a compromised robot is inside
the map, is where most of one compromised robot's harm comes from; against three it is one
mechanism of several (``docs/attack/compromised_long.md``).

This stage weighs each neighbour ``j`` whose broadcast position lies inside the map grown
by ``zone_landmarks_margin`` with its claimed covariance multiplied by
``zone_landmarks_inflation`` (``f``), in every test and in the fusion, the claim first raised
to the observer's median claim (as ``detector.redundancy_cap_fusion`` raises it):

``P'_j = f max(1, m_i / tr P_j) P_j   if   min_z ( ||p_j - c_z|| - r_z - margin ) <= 0``

(``m_i``: the median trace of the position blocks claimed by observer i's neighbours).

It discards nothing. What a lie told from inside can move a victim per step falls: with the
gates in whitened units, a lie at the gate moves the victim by about ``K nu``, with
``K ~ P_i / S`` and ``nu ~ sqrt(S)``, i.e. ``~ sqrt(1 / f)`` as much. An honest robot
inside the map keeps bridging its outside partners, with less weight (the price is
measured as the map's price: the run with nothing attacked). Withholding those links
altogether was measured first: it cuts the loop but triples the map's price (x6.3 against
x2.2 over the clean run), because the robots around the zone then lose their bridges.

What it assumes, where it fails:

* The map (as zone trust). Without an SDZ nothing changes (the clean run is unchanged).
* The broadcast position is the neighbour's claim. A compromised robot inside the map can
  move its claim out of it only by a lie at least as large as its distance to the map's
  edge plus the margin (0.25 m by default), which the other stages judge as any other
  lie. (In the simulator a compromised robot's lie is carried as the equivalent reading,
  so its broadcast position field is its honest estimate: a claim moved out of the map is
  not modelled; the margin is three to ten times the mean lie per link the gates were
  measured to accept inside the map, 25-80 mm.)
* The compiled kernel does not implement it (``compiled = False``): the correction falls
  back to the numpy path.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_redundancy_fixes import capped_claims
from resloc.cl.detection_zone import inside_zone_map
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["ZoneLandmarks", "landmark_claims"]


def landmark_claims(
    params: CLParams, x_nb: np.ndarray, P_nb: np.ndarray, i: np.ndarray
) -> np.ndarray:
    """The claimed covariances ``P_nb: (E, 3, 3)`` with those of the neighbours whose
    broadcast position ``x_nb: (E, 3)`` lies inside ``params.zone_landmarks_map`` first
    raised to the observer's median claim
    (:func:`~resloc.cl.detection_redundancy_fixes.capped_claims`
    over each observer ``i: (E,)``'s rows: a tiny claim would otherwise stay below the
    median after the inflation, and the redundancy test's own cap would undo it), then
    multiplied by ``params.zone_landmarks_inflation``. A copy when any row is inside; else
    ``P_nb`` itself."""
    if not params.zone_landmarks or not params.zone_landmarks_map:
        return P_nb
    inside = inside_zone_map(np.asarray(x_nb)[:, :2], params.zone_landmarks_map)
    if not inside.any():
        return P_nb
    out = np.array(P_nb, float)
    capped = capped_claims(out, np.asarray(i))
    out[inside] = float(params.zone_landmarks_inflation) * capped[inside]
    return out


def landmark_links(params: CLParams, links: LinkBatch) -> LinkBatch:
    """``links`` with :func:`landmark_claims` applied to their claimed covariances (what the
    reference correction and the compiled path both fuse), else ``links`` itself."""
    if not params.zone_landmarks:
        return links
    claims = landmark_claims(params, links.x_nb, links.P_nb, links.i)
    return links if claims is links.P_nb else dataclasses.replace(links, P_nb=claims)


class ZoneLandmarks:
    """The stage's place in the registry: it discards nothing (its effect is on the claimed
    covariances, :func:`landmark_links`, applied by :func:`resloc.cl.step.correct`, by the
    compiled path before its kernel (:func:`resloc.cl.kernels.fast_correct`, which then
    fuses the weakened claims as the reference does) and by the attackers' oracle)."""

    name: ClassVar[str] = "zone_landmarks"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return bool(params.zone_landmarks)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        return np.zeros(len(evidence.nu), bool)
