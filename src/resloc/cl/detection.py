"""The attack detector's stages as strategies: one declared protocol, one registry.

A link's measurement is discarded when any active stage flags it (Algorithm 1, "Attack
Detection", and the unit-aware tests of :mod:`resloc.cl.cusum`):

``gate``
    ``||Lambda_ij|| > rho`` with the detector norm: the paper's raw norm (``euclidean``),
    the noise-scaled one, or the NIS gate (``nis``, :func:`~resloc.cl.cusum.chi2_gate`).
``cusum``
    While the per-link CUSUM of the NIS alarms, measurements whose NIS exceeds ``cusum_k``.
``mean_cusum``
    While a signed CUSUM of the whitened innovation alarms, measurements beyond
    ``mean_cusum_k`` (only measurements the gate passed update it).
``robot_cusum``
    While the CUSUM of the NIS over *all* of a robot's links alarms, its measurements whose
    NIS exceeds ``robot_cusum_k`` (:mod:`resloc.cl.detection_robot`).
``redundancy``
    Discards a link whose position fix of the observer disagrees with the observer's other
    fixes of the step (leave-one-out, claimed covariances capped at a typical neighbour's:
    :mod:`resloc.cl.detection_redundancy`); against lies on one link of several, from the
    sensor or from a compromised neighbour's broadcast.
``redundancy_sequence``
    Sums each link's redundancy residuals over time (since the link was last admitted) and
    holds a link out for a while when the sum is inconsistent with zero mean: a slow lie
    inside every per-step gate accumulates evidence (:mod:`resloc.cl.detection_sequence`).
``reciprocal``
    Discards a reading whose range disagrees with the partner's reading of the same pair
    (``|r_ij - r_ji|`` against ``sqrt(2) sigma_r``, one step and in sum since the link was
    admitted; a flagged link is held out a while, then re-admitted:
    :mod:`resloc.cl.detection_reciprocal`).
``witness``
    Discards every link from a robot whose observers' notes on it (its broadcast position
    against the position each observer's estimate and reading imply), summed over time and
    robust to f lying observers, convict it (:mod:`resloc.cl.detection_witness`).
``outvoted``
    Discards nothing: a robot whose observers' witness notes on itself place it elsewhere
    than its covariance allows widens its own covariance before the correction
    (:mod:`resloc.cl.detection_outvoted`).
``startup``
    Discards nothing: for its first ``startup_steps`` corrections a robot's prior covariance
    is kept at or above a floor, so lies taken while every gate is wide cannot shrink it
    onto them (:mod:`resloc.cl.detection_startup`).
``lockout``
    Discards nothing: a robot whose detector discarded most of its links over its last
    corrections raises its prior covariance to a floor, so that its honest neighbours are
    admitted again and pull it back (:mod:`resloc.cl.detection_lockout`).
``zone_landmarks``
    Discards nothing: a neighbour whose broadcast position lies inside the (grown) SDZ map
    is weighed, in every test and in the fusion, with its claimed covariance inflated
    (:mod:`resloc.cl.detection_landmark`): a robot inside a zone is a weak landmark.
``zone_trust``
    Withholds the measurements whose observer's estimate lies inside a mapped sensing
    danger zone (:mod:`resloc.cl.detection_zone`): they are discarded and the other stages,
    the recovery included, never see them.
``recovery``
    Runs last and overrides the others: re-admits the measurements of a robot locked out by
    ``recovery_after`` consecutive rejections that pass an inflated NIS gate
    (:mod:`resloc.cl.detection_recovery`, which states the bound an attacker faces).

The CL step runs :func:`detect`; the compiled kernel's coverage is read from
:attr:`DetectorStage.compiled`. Adding a stage is one class and one line in
:data:`DETECTOR_STAGES`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar, Protocol

import numpy as np

from resloc.cl.cusum import chi2_gate, link_cusum, link_mean_cusum, nis, whiten
from resloc.cl.detection_landmark import ZoneLandmarks
from resloc.cl.detection_lockout import Lockout
from resloc.cl.detection_outvoted import Outvoted
from resloc.cl.detection_reciprocal import ReciprocalCheck
from resloc.cl.detection_recovery import RejectionRecovery
from resloc.cl.detection_redundancy import RedundancyCheck
from resloc.cl.detection_robot import RobotCusum
from resloc.cl.detection_sequence import RedundancySequence
from resloc.cl.detection_startup import StartupFloor
from resloc.cl.detection_witness import WitnessCheck
from resloc.cl.detection_zone import ZoneTrust
from resloc.cl.detector import InnovationNorm, attack_detected
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

__all__ = [
    "CHI_SQUARE_NORMS",
    "DETECTOR_STAGES",
    "NORM_GATE",
    "OPTION_CHECKS",
    "DetectorStage",
    "Evidence",
    "active_stages",
    "detect",
]


@dataclass
class Evidence:
    """What the stages judge a round of links by.

    Attributes
    ----------
    nu : ndarray, shape (E, 2)
        Innovations ``Lambda_ij`` (eq. 9).
    S : ndarray, shape (E, 2, 2)
        Their covariances ``P^zz``.
    norm : ndarray, shape (E,)
        The detector norm of ``nu``.
    i, j : ndarray of int, shape (E,)
        Observers (batch indices) and neighbours (ids).
    gated : ndarray of bool, shape (E,)
        What the gate discarded (all False until it ran or when it is off).
    detected : ndarray of bool, shape (E,), optional
        The verdict of the stages run so far (set by :func:`detect` before an overriding
        stage runs).
    inflation : ndarray, shape (E,), optional
        Set by a stage that re-admits measurements: the factor (>= 1) on the observer's
        covariance the update of each row uses (the CL step recomputes its moments).
    P_obs : ndarray, shape (E, 3, 3), optional
        The observers' covariances (the recovery bounds its inflation by their growth).
    x_obs : ndarray, shape (E, 3), optional
        The observers' estimates (zone-aware trust reads their positions).
    zone_substituted : ndarray of bool, shape (E,), optional
        Rows whose observer is inside a mapped zone and whose measurement was replaced by
        the partner's range (zone-aware trust keeps them).
    fix_excluded : ndarray of bool, shape (E,), optional
        Rows whose position fix of the observer the step's fault exclusion removed (the
        redundancy stage, :func:`resloc.cl.detection_redundancy.fix_evidence`).
    fix_statistic : ndarray, shape (E,), optional
        Their leave-one-out statistics (``nan``: not judged).
    fix_residual, fix_residual_cov : ndarray, shapes (E, 2), (E, 2, 2), optional
        Each row's fix minus its leave-one-out reference (``nan``: not judged) and that
        difference's covariance (the redundancy sequence test accumulates them).
    sequence_discard, sequence_state : ndarray, shapes (E,), (E, 6), optional
        The sequence test's verdict on each row and its link's state after the step
        (:func:`resloc.cl.detection_sequence.sequence_evidence`).
    reciprocal_discard, reciprocal_state : ndarray, shapes (E,), (E, 3), optional
        The reciprocal range check's verdict on each row and its link's state after the
        step (:func:`resloc.cl.detection_reciprocal.reciprocal_evidence`).
    """

    nu: np.ndarray
    S: np.ndarray
    norm: np.ndarray
    i: np.ndarray
    j: np.ndarray
    gated: np.ndarray
    detected: np.ndarray | None = None
    inflation: np.ndarray | None = None
    P_obs: np.ndarray | None = None
    x_obs: np.ndarray | None = None
    zone_substituted: np.ndarray | None = None
    fix_excluded: np.ndarray | None = None
    fix_statistic: np.ndarray | None = None
    fix_residual: np.ndarray | None = None
    fix_residual_cov: np.ndarray | None = None
    sequence_discard: np.ndarray | None = None
    sequence_state: np.ndarray | None = None
    reciprocal_discard: np.ndarray | None = None
    reciprocal_state: np.ndarray | None = None


class DetectorStage(Protocol):
    """One test of the attack detector.

    Attributes
    ----------
    name : str
    compiled : bool
        The compiled CL kernel (:mod:`resloc.cl.kernels`) implements the stage.
    overrides : bool
        The stage returns the final verdict from ``evidence.detected`` (the verdict so far)
        instead of adding discards to it.
    """

    name: str
    compiled: bool
    overrides: bool

    def active(self, params: CLParams) -> bool:
        """Whether ``params`` switch the stage on."""

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        """Measurements to discard, shape (E,); updates the stage's state in ``memory``."""


#: The detector norms whose square is the NIS (chi-square, 2 degrees of freedom, for honest
#: measurements): a gate on them can be set by a false-alarm probability.
CHI_SQUARE_NORMS = frozenset({InnovationNorm.NIS})


def _memory(memory: LinkMemory | None, what: str) -> LinkMemory:
    if memory is None:
        raise ValueError(f"detector {what} needs a LinkMemory")
    return memory


class NormGate:
    """``||Lambda_ij|| > rho`` with the detector norm (raw, scaled or NIS); the threshold is
    ``rho``, or set by a false-alarm probability when the norm is chi-square."""

    name: ClassVar[str] = "gate"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def problem(self, options: Any) -> str | None:
        """Why the scenario's ``[detector]`` ``options`` make no gate (names the fix)."""
        if options.false_alarm > 0.0 and options.norm not in CHI_SQUARE_NORMS:
            return (
                f"false_alarm: {options.false_alarm!r} sets a chi-square gate on the NIS; "
                f'set detector.norm = "nis" (now {options.norm.value!r}) or false_alarm = 0'
            )
        return None

    def threshold(self, options: Any) -> float:
        """The gate's ``rho`` from the scenario's detector ``options``: ``sqrt`` of the
        chi-square quantile at ``false_alarm`` when it is set, else ``rho``."""
        if options.false_alarm > 0.0:
            return math.sqrt(chi2_gate(options.false_alarm))
        return options.rho

    def active(self, params: CLParams) -> bool:
        return bool(params.detector)

    def discard(self, evidence, params, memory) -> np.ndarray:
        evidence.gated = attack_detected(evidence.norm, at_robots(params.rho, evidence.i))
        return evidence.gated


class NISCusum:
    """Per-link CUSUM of the NIS (:func:`~resloc.cl.cusum.link_cusum`)."""

    name: ClassVar[str] = "cusum"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return bool(params.cusum)

    def discard(self, evidence, params, memory) -> np.ndarray:
        memory = _memory(memory, "CUSUM (params.cusum)")
        ev = evidence
        # The gate's norm, squared, is the NIS when the norm is chi-square: no second solve.
        stat = ev.norm * ev.norm if params.detector_norm in CHI_SQUARE_NORMS else nis(ev.nu, ev.S)
        k = at_robots(params.cusum_k, ev.i)
        h = at_robots(params.cusum_h, ev.i)
        alarm = link_cusum(memory.cusum, ev.i, ev.j, stat, k, h, params.cusum_cap)
        # While a link's CUSUM alarms, its gate tightens to the CUSUM reference: measurements
        # whose own NIS is above k are discarded, honest-looking ones still pass.
        return alarm & (stat > k)


class MeanShiftCusum:
    """Signed CUSUMs of the whitened innovation (:func:`~resloc.cl.cusum.link_mean_cusum`)."""

    name: ClassVar[str] = "mean_cusum"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return bool(params.mean_cusum)

    def discard(self, evidence, params, memory) -> np.ndarray:
        memory = _memory(memory, "mean CUSUM (params.mean_cusum)")
        ev = evidence
        return link_mean_cusum(
            memory.mean_cusum,
            ev.i,
            ev.j,
            whiten(ev.nu, ev.S),
            at_robots(params.mean_cusum_k, ev.i),
            at_robots(params.mean_cusum_h, ev.i),
            ~ev.gated,
        )


#: The stages, in the order they run (zone-aware trust withholds its rows from all others:
#: a policy on the sensor, not a test; the gate first among the tests: the others read its
#: verdict; the recovery last: it overrides every verdict).
NORM_GATE = NormGate()
REDUNDANCY = RedundancyCheck()
REDUNDANCY_SEQUENCE = RedundancySequence()
RECIPROCAL = ReciprocalCheck()
OUTVOTED = Outvoted()
#: The stages that check the scenario's ``[detector]`` options (``problem(options)``).
OPTION_CHECKS = (NORM_GATE, REDUNDANCY, REDUNDANCY_SEQUENCE, RECIPROCAL, OUTVOTED)
DETECTOR_STAGES: tuple[DetectorStage, ...] = (
    ZoneTrust(),
    ZoneLandmarks(),
    NORM_GATE,
    REDUNDANCY,
    REDUNDANCY_SEQUENCE,
    RECIPROCAL,
    WitnessCheck(),
    OUTVOTED,
    StartupFloor(),
    Lockout(),
    NISCusum(),
    MeanShiftCusum(),
    RobotCusum(),
    RejectionRecovery(),
)


def active_stages(params: CLParams) -> tuple[DetectorStage, ...]:
    """The stages ``params`` switch on."""
    return tuple(s for s in DETECTOR_STAGES if s.active(params))


def detect(evidence: Evidence, params: CLParams, memory: LinkMemory | None) -> np.ndarray:
    """Run every active stage; returns the discarded measurements, shape (E,).

    A stage that *withholds* (``withholds = True``: a policy, not a test, e.g. zone-aware
    trust) runs first; the rows it discards are discarded, and the other stages judge the
    remaining rows only (their statistics and the recovery never see the withheld rows).
    """
    stages = active_stages(params)
    withheld = np.zeros(len(evidence.nu), dtype=bool)
    for stage in stages:
        if getattr(stage, "withholds", False):
            withheld |= stage.discard(evidence, params, memory)
    if withheld.any():
        keep = np.flatnonzero(~withheld)
        part = replace(
            evidence,
            **{
                f.name: value[keep]
                for f in fields(Evidence)
                if isinstance(value := getattr(evidence, f.name), np.ndarray)
            },
        )
        detected = withheld.copy()
        detected[keep] = _run_stages(part, params, memory, stages)
        evidence.gated = np.zeros(len(withheld), bool)
        evidence.gated[keep] = part.gated
        evidence.detected = detected
        if part.inflation is not None:
            evidence.inflation = np.ones(len(withheld))
            evidence.inflation[keep] = part.inflation
        return detected
    return _run_stages(evidence, params, memory, stages)


def _run_stages(
    evidence: Evidence,
    params: CLParams,
    memory: LinkMemory | None,
    stages: tuple[DetectorStage, ...],
) -> np.ndarray:
    detected = np.zeros(len(evidence.nu), dtype=bool)
    for stage in stages:
        if getattr(stage, "withholds", False):
            continue
        if stage.overrides:
            evidence.detected = detected
            detected = stage.discard(evidence, params, memory)
        else:
            detected = detected | stage.discard(evidence, params, memory)
    return detected
