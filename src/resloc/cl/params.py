"""Estimator parameters: everything a robot's CL step needs besides its data."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from resloc.cl.detector import InnovationNorm
from resloc.cl.fusion import CICriterion, FusionMethod
from resloc.errors import ConfigError

__all__ = ["CLParams", "NeighbourEstimate", "ThresholdInnovation", "UpdateMode", "at_robots"]


def at_robots(value: float | np.ndarray, idx: np.ndarray) -> float | np.ndarray:
    """A scalar parameter as is, or a per-robot parameter ``(B,)`` gathered at ``idx: (E,)``."""
    a = np.asarray(value, dtype=float)
    return a if a.ndim == 0 else a[idx]


class UpdateMode(enum.StrEnum):
    """How a robot fuses several neighbours in one step.

    ``sequential``: one Kalman update per neighbour, in ascending neighbour id, each from
    the estimate the previous one produced (the default).
    ``summed``: Algorithm 1 literally: every gain from the predicted estimate,
    ``x += sum_j K_ij Lambda_ij`` and ``P -= sum_j K_ij P^zz_ij K_ij^T``.
    """

    SEQUENTIAL = "sequential"
    SUMMED = "summed"


class NeighbourEstimate(enum.StrEnum):
    """Which estimate of neighbour j robot i uses to form ``hat z_ij`` for detector/trigger.

    ``current``: j's predicted estimate at this step (the paper: "derived from the predicted
    states hat x_i,k|k-1 and hat x_j,k|k-1").
    ``cached``: the last estimate of j that i actually received (strictly distributed);
    before the first reception the link is treated as triggered.
    In both cases a delivered transmission carries j's current predicted estimate, which
    the update then uses.
    """

    CURRENT = "current"
    CACHED = "cached"


class ThresholdInnovation(enum.StrEnum):
    """Which ``||Lambda_ij||`` enters the threshold factor ``(1 + gamma ||Lambda_ij||)``.

    ``current``: this step's innovation (the paper's notation, eq. 11).
    ``last_sent``: the innovation of the link's last delivered transmission (0 before one).
    """

    CURRENT = "current"
    LAST_SENT = "last_sent"


@dataclass(frozen=True)
class CLParams:
    """Parameters of the per-robot CL step. Scalars, or per-robot arrays of shape (B,)
    for the detector/trigger gains (so one batch can hold several configurations).

    Attributes
    ----------
    range_std, bearing_std : float
        Measurement noise standard deviations (m, rad), giving ``R``.
    odometry_std : tuple of float
        Standard deviations of measured ``v`` (m/s) and ``omega`` (rad/s).
    process_floor_std : tuple of float
        Additive process-noise floor for ``x, y, theta`` (per sqrt(s)).
    detector : bool
        Enable the attack detector.
    rho : float or ndarray (B,)
        Detection threshold on the detector norm.
    detector_norm : InnovationNorm
    trigger : bool
        Enable event triggering; when off every accepted link is transmitted.
    alpha, gamma, zeta_s, zeta_c : float or ndarray (B,)
        Event-threshold constants of eq. (11).
    trigger_norm : InnovationNorm
    risk_factor_floor : float
        Lower clip of ``(1 - zeta_s Ds - zeta_c Dc)``.
    threshold_innovation : ThresholdInnovation
    update_mode : UpdateMode
    neighbour_estimate : NeighbourEstimate
    update_without_transmission : bool
        With ``cached`` neighbour estimates: fuse an accepted but untriggered measurement
        with the cached estimate of j (no message). Off in the paper.
    fusion : FusionMethod
        The name of a registered fusion strategy: ``naive`` (the paper), ``gauge``,
        ``tracked``, ``factorized``, ``ci``, ``split_ci`` or one a caller registered
        (:mod:`resloc.cl.fusion_methods`).
    ci_criterion : CICriterion
        What the CI weight minimises: posterior ``trace`` or ``det`` of ``P_i``.
    cusum : bool
        While the per-link CUSUM of the NIS exceeds ``cusum_h``, also discard the link's
        measurements whose NIS exceeds ``cusum_k`` (:mod:`resloc.cl.cusum`; needs a
        LinkMemory). Off in the paper.
    cusum_k, cusum_h : float or ndarray (B,)
        CUSUM reference (drift) and alarm threshold, in NIS units.
    cusum_cap : float or None
        Upper bound of the CUSUM statistic (None: ``2 cusum_h``).
    mean_cusum : bool
        Also run the signed (mean-shift) CUSUMs of the whitened innovation and discard, while
        one alarms, measurements pushing its way beyond ``mean_cusum_k`` (needs a
        LinkMemory). Off in the paper.
    mean_cusum_k, mean_cusum_h : float or ndarray (B,)
        Its reference and alarm threshold, in innovation standard deviations.
    robot_cusum : bool
        Also run a CUSUM of the NIS over all of a robot's links and discard, while it alarms,
        the robot's measurements whose NIS exceeds ``robot_cusum_k``
        (:mod:`resloc.cl.detection_robot`; needs a LinkMemory).
    robot_cusum_k, robot_cusum_h : float or ndarray (B,)
        Its reference and alarm threshold, in NIS units.
    recovery : bool
        Re-admit the measurements of a robot after ``recovery_after`` consecutive rejections
        when they pass an inflated NIS gate (:mod:`resloc.cl.detection_recovery`; needs a
        LinkMemory): the detector can then never lock a robot out.
    recovery_after : float or ndarray (B,)
        ``R``: consecutive discarded measurements of one robot before recovery.
    recovery_gate : float or ndarray (B,)
        Chi-square gate on the inflated NIS (default: false-alarm probability 1e-3).
    recovery_inflation_cap : float or ndarray (B,)
        Largest inflation ``f_max`` of the innovation covariance.
    zone_trust : bool
        Discard the measurements a robot takes while its estimate lies inside a mapped
        sensing danger zone (:mod:`resloc.cl.detection_zone`).
    zone_trust_map : tuple of (cx, cy, r)
        The discs distrusted (the SDZ map, grown by the margin).
    zone_landmarks : bool
        A neighbour whose broadcast position lies inside ``zone_landmarks_map`` is weighed
        with its claimed covariance inflated (:mod:`resloc.cl.detection_landmark`).
    zone_landmarks_map : tuple of (cx, cy, r)
        The zone map grown by the landmark margin.
    zone_landmarks_inflation : float
        The factor on those neighbours' claimed covariances.
    redundancy : bool
        Discard a link whose position fix of the observer disagrees with the observer's
        other fixes of the step (:mod:`resloc.cl.detection_redundancy`).
    redundancy_gate : float or ndarray (B,)
        Chi-square gate (2 degrees of freedom) on the leave-one-out statistic.
    redundancy_min_peers : float or ndarray (B,)
        Other fixes a robot needs in a step for its links to be judged.
    redundancy_cap_fusion : bool
        Fuse each neighbour with its claimed covariance scaled up as the redundancy test
        caps it (no neighbour weighs more than the observer's median one in the update
        either: :func:`resloc.cl.detection_redundancy_fixes.capped_claims`).
    redundancy_sequence : bool
        Sum each link's redundancy residuals over time and hold a link out when the sum is
        inconsistent with zero mean (:mod:`resloc.cl.detection_sequence`).
    redundancy_sequence_gate : float or ndarray (B,)
        Chi-square gate (2 degrees of freedom) on the summed residual.
    redundancy_sequence_hold : float or ndarray (B,)
        Evaluations of a flagged link it is held out before it is re-admitted afresh.
    redundancy_sequence_forget : float or ndarray (B,)
        Discount ``lambda`` of the sums per evaluation (1: since the link was admitted).
    reciprocal : bool
        Discard a reading whose range disagrees with the partner's reading of the same pair
        (:mod:`resloc.cl.detection_reciprocal`; needs the partners' readings and a
        LinkMemory).
    reciprocal_gate : float or ndarray (B,)
        Chi-square gate (1 degree of freedom) on ``(r_ij - r_ji)^2 / (2 sigma_r^2)``.
    reciprocal_sequence_gate : float or ndarray (B,)
        Chi-square gate (1 degree of freedom) on the summed difference.
    reciprocal_hold : float or ndarray (B,)
        Evaluations of a flagged link it is held out before it is re-admitted afresh.
    reciprocal_forget : float or ndarray (B,)
        Discount ``lambda`` of the sums per evaluation (1: since the link was admitted).
    witness : bool
        Every robot's observers send notes on it (its broadcast position against the
        position their own estimate and reading imply); a per-robot sequence test on the
        notes, robust to ``witness_liars`` lying observers, discards every link from a
        robot it convicts (:mod:`resloc.cl.detection_witness`; needs a LinkMemory).
    witness_liars : float or ndarray (B,)
        ``f``: lying observers assumed per robot (the statistic drops any f notes).
    witness_k, witness_h : float or ndarray (B,)
        The sequence test's drift and alarm threshold, in chi-square (2 dof) units.
    witness_false_alarm : float
        Consistency gate of a set of notes (chi-square, 2 (n - 1) dof, this probability).
    outvoted : bool
        A robot whose observers' notes on itself (the witness notes, robust to
        ``witness_liars`` lying ones, summed with ``witness_k`` and ``witness_h``) convict
        it widens its own covariance before the correction
        (:mod:`resloc.cl.detection_outvoted`; needs ``witness``).
    outvoted_cap : float
        Largest widening factor in one step.
    outvoted_max_std : float
        No widening takes a robot's position standard deviation (the larger diagonal
        entry) beyond this, in metres; a robot already beyond it is not widened.
    startup_steps : int
        For its first this many corrections a robot's prior covariance is raised to
        ``startup_floor_std`` (:mod:`resloc.cl.detection_startup`; 0: off).
    startup_floor_std : float
        The floor: the position standard deviation (the larger diagonal entry), in metres.
    startup_decay : float
        After the ``startup_steps`` corrections the floor is not dropped but multiplied by
        this at each further correction (a geometric decay, no cliff; 0: dropped at once).
    startup_claims : bool
        While an observer's floor is raised, the claimed covariances it fuses are raised
        to the same floor (:func:`resloc.cl.detection_startup.floored_claims`).
    lockout_share : float
        A robot whose detector discarded more than this share of its judged links (an
        exponentially weighted mean over its corrections) raises its prior covariance to
        ``lockout_floor_std`` (:mod:`resloc.cl.detection_lockout`; 0: off).
    lockout_window : float
        The share's memory, in corrections (weight ``1 / lockout_window`` on the newest).
    lockout_floor_std : float
        The floor: the position standard deviation (the larger diagonal entry), in metres.
    """

    range_std: float = 0.005
    bearing_std: float = 0.05
    odometry_std: tuple[float, float] = (0.01, 0.05)
    process_floor_std: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    detector: bool = True
    rho: float | np.ndarray = 0.5
    detector_norm: InnovationNorm = InnovationNorm.EUCLIDEAN
    trigger: bool = True
    alpha: float | np.ndarray = 0.6
    gamma: float | np.ndarray = 0.5
    zeta_s: float | np.ndarray = 1.0
    zeta_c: float | np.ndarray = 1.0
    trigger_norm: InnovationNorm = InnovationNorm.EUCLIDEAN
    risk_factor_floor: float = 0.0
    threshold_innovation: ThresholdInnovation = ThresholdInnovation.CURRENT
    update_mode: UpdateMode = UpdateMode.SEQUENTIAL
    neighbour_estimate: NeighbourEstimate = NeighbourEstimate.CURRENT
    update_without_transmission: bool = False
    fusion: FusionMethod = FusionMethod.NAIVE
    ci_criterion: CICriterion = CICriterion.TRACE
    cusum: bool = False
    cusum_k: float | np.ndarray = 3.0
    cusum_h: float | np.ndarray = 20.0
    cusum_cap: float | None = None
    mean_cusum: bool = False
    mean_cusum_k: float | np.ndarray = 0.5
    mean_cusum_h: float | np.ndarray = 8.0
    robot_cusum: bool = False
    robot_cusum_k: float | np.ndarray = 3.0
    robot_cusum_h: float | np.ndarray = 30.0
    recovery: bool = False
    recovery_after: float | np.ndarray = 10.0
    recovery_gate: float | np.ndarray = 13.815510557964274
    recovery_inflation_cap: float | np.ndarray = 100.0
    zone_trust: bool = False
    zone_trust_map: tuple = ()
    zone_landmarks: bool = False
    zone_landmarks_map: tuple = ()
    zone_landmarks_inflation: float = 10.0
    redundancy: bool = False
    redundancy_gate: float | np.ndarray = 13.815510557964274
    redundancy_min_peers: float | np.ndarray = 2.0
    redundancy_cap_fusion: bool = False
    redundancy_sequence: bool = False
    redundancy_sequence_gate: float | np.ndarray = 27.631021115928547
    redundancy_sequence_hold: float | np.ndarray = 100.0
    redundancy_sequence_forget: float | np.ndarray = 1.0
    reciprocal: bool = False
    reciprocal_gate: float | np.ndarray = 10.827566170662733
    reciprocal_sequence_gate: float | np.ndarray = 23.928126976934827
    reciprocal_hold: float | np.ndarray = 100.0
    reciprocal_forget: float | np.ndarray = 0.995
    witness: bool = False
    witness_liars: float | np.ndarray = 3.0
    witness_k: float | np.ndarray = 4.0
    witness_h: float | np.ndarray = 40.0
    witness_false_alarm: float = 1e-3
    outvoted: bool = False
    outvoted_cap: float = 100.0
    outvoted_max_std: float = 0.05
    startup_steps: int = 0
    startup_floor_std: float = 0.01
    startup_decay: float = 0.0
    startup_claims: bool = False
    lockout_share: float = 0.0
    lockout_window: float = 10.0
    lockout_floor_std: float = 0.01

    def __post_init__(self) -> None:
        # The step compares choices with ``is``: coerce their string values ("summed") to
        # the enums so a plain string is not silently read as the default.
        for name, kind in _CHOICES:
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, kind(value))
            except ValueError:
                raise ConfigError(
                    f"CLParams.{name} must be one of {[k.value for k in kind]}, got {value!r}"
                ) from None

    @property
    def R(self) -> np.ndarray:
        """Measurement noise covariance, shape (2, 2)."""
        return np.diag([self.range_std**2, self.bearing_std**2])

    @property
    def noise_std(self) -> np.ndarray:
        """``[range_std, bearing_std]``, shape (2,)."""
        return np.array([self.range_std, self.bearing_std])


_CHOICES = (
    ("detector_norm", InnovationNorm),
    ("trigger_norm", InnovationNorm),
    ("threshold_innovation", ThresholdInnovation),
    ("update_mode", UpdateMode),
    ("neighbour_estimate", NeighbourEstimate),
    ("fusion", FusionMethod),
    ("ci_criterion", CICriterion),
)
