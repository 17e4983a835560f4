"""Sensing attacks inside SDZs: which links can be attacked and what is injected (eq. 5)."""

from __future__ import annotations

import enum

import numpy as np

from resloc.angles import wrap_angle

__all__ = [
    "AttackKind",
    "LinkScope",
    "StealthKnowledge",
    "apply_injection",
    "attackable_links",
    "injection",
    "link_hash_uniform",
]


class StealthKnowledge(enum.StrEnum):
    """What the stealthy attacker keeps under its threshold.

    ``full``: every test the victim runs (the gate and, if on, the CUSUM's reference).
    ``gate``: only the per-measurement gate (a CUSUM then sees its persistent excess).
    """

    FULL = "full"
    GATE = "gate"


class AttackKind(enum.StrEnum):
    """What the adversary adds to a falsified measurement, ``Gamma_ij`` of eq. (5).

    ``fixed``: ``Gamma = bias`` (range metres, bearing radians).
    ``random``: each component uniform in ``[-bias, +bias]``, drawn per measurement.
    ``gaussian``: zero-mean Gaussian with standard deviations ``bias`` (noise injection, as in
    the first author's public scripts).
    ``stealthy``: the largest injection along ``attack.stealth_direction`` that the victim's
    detector accepts (it knows robot i's predicted measurement, innovation covariance and
    detector; :mod:`resloc.world.adversary`, applied by the runner through
    ``LinkBatch.tamper``), bounded by ``bias``.
    ``replay``: the same link's honest measurement from ``attack.replay_delay`` steps ago
    (a link that did not exist then is not attacked).
    """

    FIXED = "fixed"
    RANDOM = "random"
    GAUSSIAN = "gaussian"
    STEALTHY = "stealthy"
    REPLAY = "replay"


class LinkScope(enum.StrEnum):
    """Which links an SDZ can falsify.

    ``full``: every measurement taken by a robot in the zone ("full links affected").
    ``partial``: only a fixed, seeded subset of directed links, a fraction ``link_fraction``
    of all ("partial links affected").
    """

    FULL = "full"
    PARTIAL = "partial"


_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def link_hash_uniform(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """A deterministic uniform number in ``[0, 1)`` per directed link (splitmix64 hash).

    Same ``(i, j, seed)`` gives the same value in any batch and on any machine, with no
    ``N x N`` table.

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
    seed : int

    Returns
    -------
    ndarray, shape (E,)
    """
    with np.errstate(over="ignore"):
        z = (
            np.asarray(i, np.uint64) * np.uint64(0x9E3779B97F4A7C15)
            ^ np.asarray(j, np.uint64) * np.uint64(0xD1B54A32D192ED03)
            ^ np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
        )
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def attackable_links(
    i: np.ndarray, j: np.ndarray, scope: LinkScope, fraction: float, seed: int
) -> np.ndarray:
    """Which directed links ``(i, j)`` an SDZ may falsify.

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
        Robot ids within one team (not batch indices), so every trial of a seed agrees.
    scope : LinkScope
    fraction : float
        With ``partial``, the share of attackable links.
    seed : int

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    if scope is LinkScope.FULL:
        return np.ones(len(i), dtype=bool)
    return link_hash_uniform(i, j, seed) < fraction


def injection(kind: AttackKind, bias: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Injected error ``Gamma_ij`` for ``n`` falsified measurements.

    Parameters
    ----------
    kind : AttackKind
    bias : ndarray, shape (2,)
        ``[range (m), bearing (rad)]`` magnitude.
    n : int
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (n, 2)
    """
    bias = np.asarray(bias, float)
    if kind in (AttackKind.STEALTHY, AttackKind.REPLAY):
        raise ValueError(f"attack kind {kind.value!r} is not an additive draw; see adversary.py")
    if kind is AttackKind.FIXED:
        return np.broadcast_to(bias, (n, 2)).copy()
    if kind is AttackKind.GAUSSIAN:
        return rng.normal(size=(n, 2)) * bias
    return rng.uniform(-1.0, 1.0, size=(n, 2)) * bias


def apply_injection(z: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Falsified measurement, eq. (5): ``z + Gamma`` with range kept >= 0, bearing wrapped.

    Parameters
    ----------
    z, gamma : ndarray, shape (E, 2)

    Returns
    -------
    ndarray, shape (E, 2)
    """
    out = z + gamma
    out[:, 0] = np.abs(out[:, 0])
    out[:, 1] = wrap_angle(out[:, 1])
    return out
