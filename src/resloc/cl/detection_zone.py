"""Zone-aware trust: discard what a robot's own sensor reports inside a known danger zone.

The paper's robots know the sensing danger zones (SDZ): the trigger's risk term ``Ds(i)``
is read from that map. Its threat model confines sensing attacks to the SDZs: a sensor is
falsified only while it is inside one. A team can use that directly. This stage discards
every measurement whose *observer's estimated position* lies inside a mapped zone grown by
a margin (the estimate's error), and relies on the links taken outside:

``discard_ij  <=>  min_z ( ||p_hat_i - c_z|| - r_z ) <= 0``

with ``r_z`` the mapped radius plus ``zone_trust_margin``. Measurements taken outside the
map are judged by the other stages as before. Because the decision reads only the
robot's own estimate and the map, an attacker confined to the mapped zones gains nothing
from any lie on those links, whatever it knows.

What it assumes, and where it fails (``docs/beyond.md``, "Defences that hold"):

* The threat model: attacks confined to the *mapped* zones. Where the map is wrong (a
  zone shifted, shrunk, or not mapped) or an attacker acts outside every zone, this stage
  gives nothing and the remaining stages carry the whole defence; the evaluation runs the
  defence with a shifted and a shrunk map (``detector.zone_trust_shift``,
  ``detector.zone_trust_scale``) and reports that as its honest worst case.
* A robot inside a zone does not fuse its own measurements: it dead-reckons until its
  estimate leaves the zone (its odometry bounds the error). This is a policy on the
  sensor, not an inconsistency verdict, so the rows are withheld from the other stages
  (:func:`resloc.cl.detection.detect`): the sequence tests do not accumulate the lies told
  there, and the recovery (:mod:`resloc.cl.detection_recovery`) neither counts them as a
  rejection run nor re-admits them; the recovery of a robot that left the zone works as
  before. A robot parked in a zone for good is blind for good: no statistic run by
  that robot alone can separate a lie from the truth there.
* Reciprocal position fix: a robot inside a zone is not left dead-reckoning while a
  neighbour outside measures it. When the partner ``j`` of a link ``(i, j)`` has its
  estimate outside the map and measured the same pair this step (``z_ji``, sent with j's
  estimate message: two numbers more), robot i fuses, in place of its own reading, the
  position fix ``p_j + r_ji [cos(theta_j + b_ji), sin(theta_j + b_ji)]`` with its
  covariance from j's estimate and sensor noise (:func:`reciprocal_position_fix`, a
  linear measurement of ``x_i``'s position). Only links with no trusted partner reading
  are discarded. (A range-only substitution was tried first: with 7-13 of the 17 robots
  inside the early zone it left the honest run at about 100x the MSLE of the run without
  zones; rejection alone at 800x.)
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, NeighbourEstimate
from resloc.filters.base import Moments

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "ZoneTrust",
    "inside_zone_map",
    "materialize_with_reciprocal",
    "reciprocal_position_fix",
    "reciprocal_rows",
    "substitute_reciprocal",
    "zone_map",
]


def zone_map(
    zones: list[tuple[tuple[float, float], float]],
    margin: float = 0.0,
    shift: tuple[float, float] = (0.0, 0.0),
    scale: float = 1.0,
) -> tuple[tuple[float, float, float], ...]:
    """The discs the defence distrusts: each zone's centre moved by ``shift`` and its
    radius ``scale * radius + margin``.

    Parameters
    ----------
    zones : list of ((x, y), radius)
        The sensing danger zones the team was given (m).
    margin : float
        Added to every radius (m): the estimated position's error.
    shift : (float, float)
        Map error for evaluation: the mapped centres moved by this (m).
    scale : float
        Map error for evaluation: the mapped radii multiplied by this.

    Returns
    -------
    tuple of (cx, cy, r)
        Hashable (it sits in the frozen :class:`~resloc.cl.params.CLParams`).
    """
    return tuple(
        (
            float(c[0]) + float(shift[0]),
            float(c[1]) + float(shift[1]),
            max(float(scale) * float(r) + float(margin), 0.0),
        )
        for c, r in zones
    )


def inside_zone_map(p: np.ndarray, discs: tuple[tuple[float, float, float], ...]) -> np.ndarray:
    """Whether positions lie inside any disc of the map.

    Parameters
    ----------
    p : ndarray, shape (E, 2)
        Positions (m).
    discs : tuple of (cx, cy, r)

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    p = np.asarray(p, float)
    if not discs:
        return np.zeros(len(p), bool)
    d = np.asarray(discs, float)  # (Z, 3)
    gap = np.hypot(p[:, None, 0] - d[None, :, 0], p[:, None, 1] - d[None, :, 1]) - d[None, :, 2]
    return (gap <= 0.0).any(axis=1)


class ZoneTrust:
    """Discard measurements whose observer's estimate lies inside the mapped SDZs.

    It withholds its rows from every other stage (a policy on the sensor, not a verdict:
    the per-link statistics and the recovery never see them) and needs the observers'
    estimates (``Evidence.x_obs``); without them (an attacker's scratch copy of the
    detector) it discards nothing.

    Its compiled twin (:mod:`resloc.cl.kernels_zone`) decides in the link loops and fuses
    the partner's position fix with the Kalman update of the naive fusion
    (:meth:`kernel_refusal` names what it does not cover).
    """

    name: ClassVar[str] = "zone_trust"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False
    #: Its rows are withheld from every other stage (:func:`resloc.cl.detection.detect`).
    withholds: ClassVar[bool] = True

    def active(self, params: CLParams) -> bool:
        return bool(params.zone_trust)

    def kernel_refusal(self, params: CLParams) -> str | None:
        """Why the compiled twin does not run with ``params`` (None: it does)."""
        strategy = fusion_strategy(params.fusion)
        if strategy.kernel_update != "kalman" or strategy.kernel_bookkeeping != "none":
            return (
                f"the detector stage 'zone_trust' has a compiled twin for the naive fusion "
                f"only (fusion {params.fusion.value!r} updates with the position fix in Python)"
            )
        if params.neighbour_estimate is not NeighbourEstimate.CURRENT:
            return "the detector stage 'zone_trust' has no compiled twin with cached estimates"
        return None

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if evidence.x_obs is None:
            return np.zeros(len(evidence.nu), bool)
        inside = inside_zone_map(evidence.x_obs[:, :2], params.zone_trust_map)
        if evidence.zone_substituted is not None:
            inside &= ~evidence.zone_substituted
        return inside


def reciprocal_rows(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Row of the reverse link ``(j, i)`` of every row ``(i, j)``; -1 where there is none.

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
        Observers and neighbours (batch indices: the simulator's links of one step).

    Returns
    -------
    ndarray of int, shape (E,)
    """
    i = np.asarray(i, np.int64)
    j = np.asarray(j, np.int64)
    if len(i) == 0:
        return np.zeros(0, np.int64)
    width = int(max(i.max(), j.max())) + 1
    keys = i * width + j
    order = np.argsort(keys, kind="stable")
    want = j * width + i
    pos = np.clip(np.searchsorted(keys[order], want), 0, len(i) - 1)
    found = keys[order][pos] == want
    return np.where(found, order[pos], -1)


def materialize_with_reciprocal(links: LinkBatch, z_hat: np.ndarray, S: np.ndarray) -> LinkBatch:
    """The step's links with every measurement as reported and its reverse link's reading.

    An adversary's ``tamper`` hook is applied to every row at once, against the victim's
    predicted measurements ``z_hat: (E, 2)`` and innovation covariances ``S: (E, 2, 2)``
    (the lie is physically injected when the sensor reads, before any update of this
    step), so the range a partner reports is the one it actually sends, lie included.

    Returns
    -------
    LinkBatch
        ``z`` as reported, ``tamper`` None, ``z_reciprocal: (E, 2)`` the reverse link's
        reported range and bearing (``nan`` where the batch holds no reverse link).
    """
    z = links.z if links.tamper is None else links.tamper(np.arange(len(links)), z_hat, S)
    reverse = reciprocal_rows(links.i, links.j)
    partner = np.where((reverse >= 0)[:, None], z[np.maximum(reverse, 0)], np.nan)
    return dataclasses.replace(links, z=np.asarray(z, float), tamper=None, z_reciprocal=partner)


def substitute_reciprocal(
    x_i: np.ndarray,
    x_nb: np.ndarray,
    z_reciprocal: np.ndarray | None,
    params: CLParams,
) -> np.ndarray:
    """Rows whose observer is inside the map and whose partner, outside it, measured the
    pair (their measurement becomes the partner's position fix).

    Parameters
    ----------
    x_i, x_nb : ndarray, shape (E, 3)
        Observers' estimates and the neighbours' (as their messages carry them).
    z_reciprocal : ndarray, shape (E, 2) or None
    params : CLParams

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    if z_reciprocal is None:
        return np.zeros(len(x_i), bool)
    inside = inside_zone_map(x_i[:, :2], params.zone_trust_map)
    partner_outside = ~inside_zone_map(x_nb[:, :2], params.zone_trust_map)
    return inside & partner_outside & np.isfinite(z_reciprocal).all(axis=1)


def reciprocal_position_fix(
    x_i: np.ndarray,
    P_i: np.ndarray,
    x_j: np.ndarray,
    P_j: np.ndarray,
    z_ji: np.ndarray,
    R: np.ndarray,
) -> tuple[Moments, np.ndarray]:
    """Robot i's position as neighbour j measured it: a linear measurement of ``x_i``.

    ``p_fix = p_j + r_ji u(a)``, ``a = theta_j + b_ji``, ``u(a) = [cos a, sin a]``, with
    covariance ``C = J_j P_j J_j^T + J_z R J_z^T`` (first order in j's pose and j's
    sensor noise; j's estimate is treated as independent of i's, as naive fusion does).
    The measurement model is ``h(x_i) = [x_i, y_i]``, ``H = [I_2 0]``.

    Parameters
    ----------
    x_i, P_i : ndarray, shapes (E, 3), (E, 3, 3)
        Observer i's estimate.
    x_j, P_j : ndarray, shapes (E, 3), (E, 3, 3)
        Neighbour j's estimate (what its message carries).
    z_ji : ndarray, shape (E, 2)
        j's range and bearing of i.
    R : ndarray, shape (2, 2)
        Range/bearing noise covariance of j's sensor.

    Returns
    -------
    moments : Moments
        ``z_hat = p_i``, ``S = P_i,pos + C``, ``Pxz = P_i[:, :, :2]``, ``H_i``, ``R_eff = C``.
    nu : ndarray, shape (E, 2)
        ``p_fix - p_i`` (m; not an angle: never wrapped).
    """
    r, a = z_ji[:, 0], x_j[:, 2] + z_ji[:, 1]
    c, s = np.cos(a), np.sin(a)
    E = len(r)
    J_j = np.zeros((E, 2, 3))
    J_j[:, 0, 0] = J_j[:, 1, 1] = 1.0
    J_j[:, 0, 2], J_j[:, 1, 2] = -r * s, r * c
    J_z = np.stack([np.stack([c, -r * s], axis=1), np.stack([s, r * c], axis=1)], axis=1)
    C = J_j @ P_j @ np.swapaxes(J_j, -1, -2) + J_z @ R @ np.swapaxes(J_z, -1, -2)
    H = np.zeros((E, 2, 3))
    H[:, 0, 0] = H[:, 1, 1] = 1.0
    p_fix = x_j[:, :2] + r[:, None] * np.stack([c, s], axis=1)
    S = P_i[:, :2, :2] + C
    moments = Moments(
        x_i[:, :2].copy(), 0.5 * (S + np.swapaxes(S, -1, -2)), P_i[:, :, :2].copy(), H, C
    )
    return moments, p_fix - x_i[:, :2]
