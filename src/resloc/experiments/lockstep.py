"""One estimator loop for simulated and replayed data.

A *step source* (the simulated :class:`~resloc.world.world.World` of
:func:`~resloc.experiments.runner.run_scenario`, or a recorded MRCLAM dataset of
:func:`~resloc.experiments.mrclam.run_mrclam`) produces each step's odometry and link groups
as a :class:`Step`, and records what every estimator made of it. :func:`run_lockstep` runs
every estimator through every step on the same data (common random numbers), each step of
each estimator timed and isolated: a numerical failure or a non-finite estimate stops that
estimator (:attr:`EstimatorState.diverged`), not the run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from resloc.cl.fusion_methods import FusionStrategy
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.cl.step import LinkBatch, LinkOutcome, correct, predict
from resloc.errors import NumericalError
from resloc.filters.base import GaussianFilter
from resloc.linalg import symmetrize

__all__ = [
    "DEAD_RECKONING",
    "Estimation",
    "EstimatorState",
    "LinkGroup",
    "Step",
    "StepSource",
    "divergence",
    "run_lockstep",
]

#: Name of the odometry-only baseline in results.
DEAD_RECKONING = "dr"

_NO_EDGES = (np.empty(0, np.int64), np.empty(0, np.int64))


@dataclass
class LinkGroup:
    """Links of one step fused by one :func:`~resloc.cl.step.correct` call: observers ``i``,
    observed nodes ``j``, ``z`` and ``channel_ok`` (shapes (E,), (E,), (E, 2), (E,), sorted
    by ``i``); ``params`` (None: the run's); ``fixed`` neighbour states ``(E, 3)``,
    ``(E, 3, 3)`` of nodes that are not estimated (MRCLAM landmarks; None: the estimator's
    current estimates of robots ``j``); further ``LinkBatch`` fields ``extras`` (the stealthy
    attacker's ``tamper``); ``rows``, where the links sit in the source's own log."""

    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    channel_ok: np.ndarray
    params: CLParams | None = None
    fixed: tuple[np.ndarray, np.ndarray] | None = None
    extras: dict = field(default_factory=dict)
    rows: np.ndarray | None = None


@dataclass
class Step:
    """What every estimator's step ``k`` (0-based) shares: odometry ``u: (B, 2)``, the link
    ``groups`` corrected in order (each from the estimates the previous ones left), the
    true-position risks ``risk_s``, ``risk_c`` and ``lambda2`` (each (B,)), the links that
    carry a message (``comm_edges``, for a fusion method's exchanges) and the adversary's
    ``attack_step``."""

    k: int
    u: np.ndarray
    groups: list[LinkGroup]
    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    comm_edges: tuple[np.ndarray, np.ndarray] = _NO_EDGES
    attack_step: object = None


@dataclass(frozen=True)
class Estimation:
    """What every estimator's step shares over a run: ``params`` (prediction, and groups
    without their own), ``dt``, ``robots`` per trial (names a divergence's robot),
    ``risk_zones`` (SDZ, CDZ) whose risk the trigger takes at the predicted estimates
    (``trigger.risk_source = "estimated"``; None: the true-position risks) and the
    ``adversary`` (a strategy of :mod:`resloc.world.attackers`)."""

    params: CLParams
    dt: float
    robots: int
    risk_zones: tuple | None = None
    adversary: object = None


class EstimatorState:
    """One estimator during a run: filter, estimates ``x: (B, 3)``, ``P: (B, 3, 3)``, link
    memory over ``nodes`` ids (robots and fixed neighbours), wall time, ``diverged`` and
    the last step's outcomes (one per link group). ``fusion`` None: dead reckoning."""

    def __init__(
        self,
        name: str,
        filt: GaussianFilter,
        x0: np.ndarray,
        P0: np.ndarray,
        nodes: int,
        fusion: FusionStrategy | None = None,
    ):
        self.name, self.filt, self.fusion = name, filt, fusion
        self.x, self.P = x0.copy(), P0.copy()
        self.memory = LinkMemory(nodes)
        self.wall = 0.0
        self.diverged: dict | None = None
        self.outcomes: list[LinkOutcome] = []
        self.pending_P: np.ndarray | None = None


class StepSource(Protocol):
    """Simulated or replayed data, as :func:`run_lockstep` consumes it."""

    def steps(self) -> Iterable[Step]: ...

    def record(self, est: EstimatorState, step: Step) -> None: ...


def run_lockstep(
    source: StepSource,
    estimators: list[EstimatorState],
    setup: Estimation,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Every estimator through every step of ``source``, in lockstep.

    ``source`` is simulated or replayed data: ``source.steps()`` yields its :class:`Step`
    objects in order, ``source.record(est, step)`` keeps what ``est`` made of ``step``
    (``est.diverged`` set: it has stopped; it is still recorded at every later step).
    ``progress(k)`` is called after step ``k`` (1-based).
    """
    for step in source.steps():
        for est in estimators:
            if est.diverged is None:
                _isolated_step(est, step, setup)
            source.record(est, step)
        if progress is not None:
            progress(step.k + 1)


def _isolated_step(est: EstimatorState, step: Step, setup: Estimation) -> None:
    """:func:`_step_estimator`, timed; a numerical failure or a non-finite estimate stops
    this estimator (``est.diverged``) instead of the run: the others' results must not be
    lost to one filter's divergence."""
    t0 = time.perf_counter()
    est.pending_P = None
    try:
        _step_estimator(est, step, setup)
    except (NumericalError, np.linalg.LinAlgError, FloatingPointError) as exc:
        last = est.pending_P if est.pending_P is not None else est.P
        est.diverged = divergence(step.k, setup.dt, setup.robots, last, str(exc))
        return
    finally:
        est.wall += time.perf_counter() - t0
    if not (np.isfinite(est.x).all() and np.isfinite(est.P).all()):
        reason = "the estimate became NaN or infinite"
        est.diverged = divergence(step.k, setup.dt, setup.robots, est.P, reason)


def _step_estimator(est: EstimatorState, step: Step, setup: Estimation) -> None:
    """One step (predict, each link group's correction, exchange) of one estimator; sets
    ``est.x``, ``est.P``, ``est.outcomes`` (and ``est.pending_P``, the predicted
    covariance, for divergence reports)."""
    params, dt, fusion = setup.params, setup.dt, est.fusion
    xp, Pp = predict(est.filt, est.x, est.P, step.u, dt, params)
    est.pending_P = Pp
    if fusion is None:  # dead reckoning: the odometry alone
        est.x, est.P, est.outcomes = xp, Pp, []
        return
    Pp = fusion.predict(est.memory, est.x, step.u, dt, params, Pp)
    risk_s, risk_c = step.risk_s, step.risk_c
    if setup.risk_zones is not None:
        sdz, cdz = setup.risk_zones
        risk_s = sdz.risk(xp[:, :2]) if sdz else risk_s
        risk_c = cdz.risk(xp[:, :2]) if cdz else risk_c
    x, P = xp, Pp
    outcomes = []
    for group in step.groups:
        fields = {**fusion.link_fields(est.memory, group.j), **group.extras}
        common = (group.channel_ok, risk_s, risk_c, step.lambda2)
        if group.fixed is None:  # neighbours are batch members: read by index, no copy
            links = LinkBatch.from_predicted(group.i, group.j, group.z, x, P, *common, **fields)
        else:
            links = LinkBatch(group.i, group.j, group.z, *group.fixed, *common, **fields)
        if setup.adversary is not None:
            links = setup.adversary.attack(links, step.attack_step, params, est.memory)
        group_params = params if group.params is None else group.params
        x, P, out = correct(est.filt, x, P, links, group_params, est.memory)
        outcomes.append(out)
    est.x, est.P, est.outcomes = x, P, outcomes
    fusion.exchange(est.memory, *step.comm_edges)


def divergence(k: int, dt: float, N: int, P: np.ndarray, reason: str) -> dict:
    """Describe a divergence at step index ``k``: when, and which robot.

    The failing computation may be inside a link update, so the robot is the one whose
    covariance among ``P`` (shape ``(T * N, 3, 3)``, the last one computed) is non-finite
    or closest to singular (smallest eigenvalue relative to its trace).

    Returns
    -------
    dict
        ``step`` (1-based), ``time_s``, ``trial``, ``robot``, ``min_eigenvalue``, ``reason``.
    """
    P = np.asarray(P, dtype=float)
    finite = np.all(np.isfinite(P), axis=(-1, -2))
    score = np.full(len(P), -np.inf)
    if finite.any():
        Pf = symmetrize(P[finite])
        eig = np.linalg.eigvalsh(Pf)[:, 0]
        trace = np.maximum(np.trace(Pf, axis1=-2, axis2=-1), 1e-300)
        score[finite] = eig / trace
    b = int(np.argmin(score)) if len(P) else 0
    min_eig = float(np.linalg.eigvalsh(symmetrize(P[b]))[0]) if finite[b] else float("nan")
    return {
        "step": k + 1,
        "time_s": round((k + 1) * dt, 9),
        "trial": b // N,
        "robot": b % N,
        "min_eigenvalue": min_eig,
        "reason": reason.splitlines()[0] if reason else "",
    }
