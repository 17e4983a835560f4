"""Scenario files: the schema (one frozen dataclass per TOML table) and the embedded default.

A scenario is a TOML file with the tables ``[run]``, ``[team]``, ``[motion]``,
``[sensing]``, ``[estimator]``, ``[detector]``, ``[trigger]``, ``[attack]`` and the arrays of
tables ``[[sdz]]`` and ``[[cdz]]``. Every key is optional (defaults below); an unknown key, a
wrong type or an out-of-range value raises :class:`~resloc.errors.ConfigError` with one line
naming the field, the value and the fix. The strict parsing lives in
:mod:`resloc.experiments.config_parse`, the TOML writing in :mod:`resloc.experiments.config_dump`.
"""

from __future__ import annotations

import enum
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import NORM_GATE
from resloc.cl.detection_zone import zone_map
from resloc.cl.detector import InnovationNorm
from resloc.cl.fusion import CICriterion, FusionMethod
from resloc.cl.fusion_methods import FUSION_STRATEGIES
from resloc.cl.gauge import GaugeSums
from resloc.cl.graph import Lambda2Source
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.schema import option
from resloc.validation import INT64_MAX
from resloc.world.spec import (
    ARENA_MAX,
    AttackSpec,
    MotionSpec,
    SensingSpec,
    TeamSpec,
    WorldSpec,
)

__all__ = [
    "SCENARIO_TABLES",
    "ZONE_TABLES",
    "DetectorSpec",
    "EstimatorSpec",
    "RiskSource",
    "RunSpec",
    "Scenario",
    "TriggerSpec",
    "default_scenario",
]


class RiskSource(enum.StrEnum):
    """Where a robot evaluates ``Ds(i)``, ``Dc(i)`` for its trigger: at its true position
    (the zones are sensed) or at its own position estimate (a known risk map)."""

    TRUE = "true"
    ESTIMATED = "estimated"


@dataclass(frozen=True)
class RunSpec:
    """What to run."""

    name: str = option("arc-turn", "scenario name (one printable line)")
    seed: int = option(
        0, "random seed of the world (truth, noise, attacks, channel)", min=0, max=INT64_MAX
    )
    steps: int = option(1000, "number of time steps", min=1, max=10_000_000)
    trials: int = option(
        1,
        "Monte Carlo trials simulated together (seeds seed.0 .. seed.T-1)",
        min=1,
        max=5_000_000,
    )
    filters: list = option(["ckf", "ukf", "ekf"], "filters to run: any of ckf, ukf, ekf")
    dead_reckoning: bool = option(True, "also run odometry-only dead reckoning as a floor")


@dataclass(frozen=True)
class EstimatorSpec:
    """Per-robot filter options (see ``docs/algorithm.md``)."""

    update_mode: UpdateMode = option(UpdateMode.SEQUENTIAL, "sequential or summed neighbour fusion")
    neighbour_estimate: NeighbourEstimate = option(
        NeighbourEstimate.CURRENT, "neighbour estimate for detector/trigger: current or cached"
    )
    update_without_transmission: bool = option(
        False, "with cached estimates, fuse untriggered measurements with the cache"
    )
    ukf_alpha: float = option(0.5, "UKF alpha (scaled sigma points)", min=1e-4, max=1.0)
    ukf_beta: float = option(2.0, "UKF beta", min=0.0, max=100.0)
    ukf_kappa: float = option(
        0.0, "UKF kappa (n + kappa > 0 with n = 3: kappa > -3)", gt=-3.0, max=100.0
    )
    fusion: FusionMethod = option(
        FusionMethod.NAIVE,
        f"neighbour fusion: {', '.join(FUSION_STRATEGIES)} (naive: the paper; docs/beyond.md)",
    )
    ci_criterion: CICriterion = option(CICriterion.TRACE, "CI weight minimises trace or det of P_i")
    gauge_sums: GaugeSums = option(
        GaugeSums.EXACT,
        "gauge fusion's team sums: exact, or each robot's own by neighbour consensus",
    )
    gauge_rounds: int = option(
        3, "gauge sums by consensus: neighbour exchanges per step", min=1, max=1000
    )


@dataclass(frozen=True)
class DetectorSpec:
    """Innovation-residual attack detector (Algorithm 1)."""

    enabled: bool = option(True, "discard measurements whose innovation norm exceeds rho")
    rho: float = option(0.5, "detection threshold rho (units of the chosen norm)", gt=0.0, max=1e6)
    norm: InnovationNorm = option(
        InnovationNorm.EUCLIDEAN, "innovation norm: euclidean, scaled, nis"
    )
    false_alarm: float = option(
        0.0,
        "with norm = nis: chi-square gate at this false-alarm probability (0: use rho)",
        min=0.0,
        max=0.5,
    )
    cusum: bool = option(False, "also discard while the per-link CUSUM of the NIS exceeds cusum_h")
    cusum_k: float = option(3.0, "CUSUM reference (drift) in NIS units", gt=0.0, max=1e6)
    cusum_h: float = option(20.0, "CUSUM alarm threshold in NIS units", gt=0.0, max=1e6)
    mean_cusum: bool = option(
        False, "also discard while a signed CUSUM of the whitened innovation exceeds mean_cusum_h"
    )
    mean_cusum_k: float = option(
        0.5, "mean-shift CUSUM reference, in innovation sigmas", gt=0.0, max=1e6
    )
    mean_cusum_h: float = option(
        8.0, "mean-shift CUSUM alarm threshold, in sigmas", gt=0.0, max=1e6
    )
    robot_cusum: bool = option(
        False, "also discard while the CUSUM of the NIS over all of a robot's links alarms"
    )
    robot_cusum_k: float = option(3.0, "per-robot CUSUM reference in NIS units", gt=0.0, max=1e6)
    robot_cusum_h: float = option(
        30.0, "per-robot CUSUM alarm threshold in NIS units", gt=0.0, max=1e6
    )
    recovery: bool = option(
        False, "re-admit a robot's measurements after recovery_after consecutive rejections"
    )
    recovery_after: int = option(
        10, "consecutive rejections of one robot before recovery", min=1, max=1_000_000
    )
    recovery_false_alarm: float = option(
        1e-3, "recovery: chi-square gate on the inflated NIS at this probability", gt=0.0, max=0.5
    )
    recovery_inflation_cap: float = option(
        100.0, "recovery: largest inflation of the innovation covariance", min=1.0, max=1e12
    )
    # Defences that use what a team knows (docs/beyond.md, "Defences that hold").
    zone_trust: bool = option(
        False,
        "inside a mapped SDZ (estimated position) a robot ignores its own readings and fuses "
        "its outside neighbours' readings of it",
    )
    zone_trust_margin: float = option(
        0.05, "zone trust: grow every mapped SDZ radius by this (m)", min=0.0, max=ARENA_MAX
    )
    zone_trust_shift: list = option(
        [0.0, 0.0],
        "zone trust: the map's error for evaluation, centres moved by [dx, dy] (m)",
        min=-ARENA_MAX,
        max=ARENA_MAX,
    )
    zone_trust_scale: float = option(
        1.0, "zone trust: the map's error for evaluation, radii times this", min=0.0, max=1e3
    )
    zone_landmarks: bool = option(
        False,
        "a neighbour whose broadcast position lies inside a mapped SDZ (the zone trust map "
        "grown by zone_landmarks_margin) is weighed with its claimed covariance inflated",
    )
    zone_landmarks_inflation: float = option(
        10.0, "zone landmarks: the factor on those neighbours' claimed covariance", min=1.0, max=1e6
    )
    zone_landmarks_margin: float = option(
        0.25, "zone landmarks: grow the zone trust map by this more (m)", min=0.0, max=ARENA_MAX
    )
    redundancy: bool = option(
        False,
        "discard a link whose fix of the robot's position disagrees with its other "
        "neighbours' fixes (claimed covariances capped at a typical neighbour's)",
    )
    redundancy_false_alarm: float = option(
        1e-3, "redundancy: chi-square gate at this false-alarm probability", gt=0.0, max=0.5
    )
    redundancy_min_peers: int = option(
        2,
        "redundancy: other fixes a robot needs in a step for its links to be judged",
        min=1,
        max=1000,
    )
    redundancy_cap_fusion: bool = option(
        False,
        "redundancy: also fuse each neighbour with its claimed covariance capped as the "
        "test caps it (no neighbour weighs more than the median one in the update)",
    )
    redundancy_sequence: bool = option(
        False,
        "redundancy: also sum each link's residuals over time and hold a link out for a "
        "while when the sum is inconsistent with zero mean (a slow lie accumulates evidence)",
    )
    redundancy_sequence_false_alarm: float = option(
        1e-6,
        "redundancy sequence: chi-square gate at this false-alarm probability",
        gt=0.0,
        max=0.5,
    )
    redundancy_sequence_hold: int = option(
        100, "redundancy sequence: evaluations a flagged link is held out", min=1, max=1_000_000
    )
    redundancy_sequence_forget: float = option(
        1.0,
        "redundancy sequence: discount of the sums per evaluation (1: none)",
        gt=0.0,
        max=1.0,
    )
    reciprocal: bool = option(
        False,
        "discard a reading whose range disagrees with the partner's reading of the same "
        "pair (one step, and in sum: a flagged link is held out, then re-admitted)",
    )
    reciprocal_false_alarm: float = option(
        1e-3,
        "reciprocal: one-step chi-square gate at this false-alarm probability",
        gt=0.0,
        max=0.5,
    )
    reciprocal_sequence_false_alarm: float = option(
        1e-6, "reciprocal: summed chi-square gate at this false-alarm probability", gt=0.0, max=0.5
    )
    reciprocal_hold: int = option(
        100, "reciprocal: evaluations a flagged link is held out", min=1, max=1_000_000
    )
    reciprocal_forget: float = option(
        0.995,
        "reciprocal: discount of the sums per evaluation (1: none; 0.995: a window of about "
        "200 evaluations, so a long honest history does not dilute a late liar's lead)",
        gt=0.0,
        max=1.0,
    )
    witness: bool = option(
        False,
        "every robot's observers send notes on it (its broadcast position against their "
        "estimate and reading); a robot the notes convict over time (robust to witness_liars "
        "lying observers) is ignored until they clear it (docs/attack/witness.md)",
    )
    witness_liars: int = option(
        3,
        "witness: lying observers assumed per robot (any this many notes are dropped)",
        min=0,
        max=100,
    )
    witness_k: float = option(
        4.0, "witness: sequence-test drift per step (chi-square units)", gt=0.0, max=1e6
    )
    witness_h: float = option(
        40.0, "witness: sequence-test alarm threshold (chi-square units)", gt=0.0, max=1e6
    )
    witness_false_alarm: float = option(
        1e-3, "witness: consistency gate of a set of notes at this probability", gt=0.0, max=0.5
    )
    outvoted: bool = option(
        False,
        "a robot whose observers' witness notes on itself convict it (the witness test) "
        "widens its own covariance (docs/attack/outvoted.md; needs witness)",
    )
    outvoted_cap: float = option(
        100.0, "outvoted: the largest widening of its covariance in one step", min=1.0, max=1e6
    )
    outvoted_max_std: float = option(
        0.05,
        "outvoted: no widening takes a position standard deviation beyond this (m)",
        gt=0.0,
        max=1e6,
    )
    startup_steps: int = option(
        0,
        "for its first this many corrections a robot's covariance is kept at or above "
        "startup_floor_std (docs/attack/startup.md; 0: off)",
        min=0,
        max=1_000_000,
    )
    startup_floor_std: float = option(
        0.01, "startup: the floor of a position standard deviation (m)", gt=0.0, max=1e6
    )
    startup_decay: float = option(
        0.0,
        "startup: after startup_steps the floor is multiplied by this per correction "
        "(0: dropped at once, the old cliff; 1: never released)",
        min=0.0,
        max=1.0,
    )
    startup_claims: bool = option(
        False,
        "startup: while an observer's floor is raised, the claims it fuses are raised to "
        "the same floor (docs/attack/lockout.md)",
    )
    lockout_share: float = option(
        0.0,
        "a robot whose detector discarded more than this share of its links (a mean over "
        "lockout_window corrections) raises its covariance to lockout_floor_std "
        "(docs/attack/lockout.md; 0: off)",
        min=0.0,
        max=1.0,
    )
    lockout_window: float = option(
        10.0, "lockout: the share's memory, in corrections", min=1.0, max=1e6
    )
    lockout_floor_std: float = option(
        0.01, "lockout: the floor of a position standard deviation (m)", gt=0.0, max=1e6
    )


@dataclass(frozen=True)
class TriggerSpec:
    """Adaptive event trigger, eq. (11)."""

    enabled: bool = option(True, "event-triggered communication (off: transmit every step)")
    alpha: float = option(0.6, "alpha of eq. (11)", min=0.0, max=1e6)
    gamma: float = option(0.5, "gamma of eq. (11)", min=0.0, max=1e6)
    zeta_s: float = option(1.0, "weight of the sensing risk Ds(i)", min=-100.0, max=100.0)
    zeta_c: float = option(1.0, "weight of the communication risk Dc(i)", min=-100.0, max=100.0)
    norm: InnovationNorm = option(
        InnovationNorm.EUCLIDEAN, "innovation norm: euclidean, scaled, nis"
    )
    lambda2: Lambda2Source = option(
        Lambda2Source.COMPONENT,
        "lambda2 of the robot's component, of the global graph, or each robot's distributed "
        "estimate",
    )
    lambda2_rounds: int = option(
        3, "distributed lambda2: neighbour exchanges per step", min=1, max=1000
    )
    risk_factor_floor: float = option(
        0.0, "lower clip of (1 - zeta_s Ds - zeta_c Dc)", min=-100.0, max=100.0
    )
    threshold_innovation: ThresholdInnovation = option(
        ThresholdInnovation.CURRENT, "innovation inside the threshold: current or last_sent"
    )
    risk_source: RiskSource = option(RiskSource.TRUE, "Ds/Dc at the true or estimated position")


@dataclass(frozen=True)
class Scenario:
    """A complete, validated scenario."""

    run: RunSpec = field(default_factory=RunSpec)
    world: WorldSpec = field(default_factory=WorldSpec)
    estimator: EstimatorSpec = field(default_factory=EstimatorSpec)
    detector: DetectorSpec = field(default_factory=DetectorSpec)
    trigger: TriggerSpec = field(default_factory=TriggerSpec)

    def cl_params(self) -> CLParams:
        """The per-robot estimator parameters of this scenario."""
        w, d, t, e = self.world, self.detector, self.trigger, self.estimator
        return CLParams(
            range_std=w.sensing.range_std,
            bearing_std=w.sensing.bearing_std,
            odometry_std=tuple(w.motion.odometry_std),
            process_floor_std=tuple(w.motion.process_floor_std),
            detector=d.enabled,
            rho=NORM_GATE.threshold(d),
            detector_norm=d.norm,
            trigger=t.enabled,
            alpha=t.alpha,
            gamma=t.gamma,
            zeta_s=t.zeta_s,
            zeta_c=t.zeta_c,
            trigger_norm=t.norm,
            risk_factor_floor=t.risk_factor_floor,
            threshold_innovation=t.threshold_innovation,
            update_mode=e.update_mode,
            neighbour_estimate=e.neighbour_estimate,
            update_without_transmission=e.update_without_transmission,
            fusion=e.fusion,
            ci_criterion=e.ci_criterion,
            cusum=d.cusum,
            cusum_k=d.cusum_k,
            cusum_h=d.cusum_h,
            mean_cusum=d.mean_cusum,
            mean_cusum_k=d.mean_cusum_k,
            mean_cusum_h=d.mean_cusum_h,
            robot_cusum=d.robot_cusum,
            robot_cusum_k=d.robot_cusum_k,
            robot_cusum_h=d.robot_cusum_h,
            recovery=d.recovery,
            recovery_after=float(d.recovery_after),
            # The gate's quantile needs scipy.special (a third of a second to import);
            # without recovery nothing reads it, and CLParams keeps its default.
            **({"recovery_gate": chi2_gate(d.recovery_false_alarm)} if d.recovery else {}),
            recovery_inflation_cap=d.recovery_inflation_cap,
            zone_trust=d.zone_trust,
            zone_trust_map=zone_map(
                [(z.center, z.radius) for z in w.sdz] if d.zone_trust else [],
                d.zone_trust_margin,
                tuple(d.zone_trust_shift),
                d.zone_trust_scale,
            ),
            zone_landmarks=d.zone_landmarks,
            zone_landmarks_inflation=float(d.zone_landmarks_inflation),
            zone_landmarks_map=zone_map(
                [(z.center, z.radius) for z in w.sdz] if d.zone_landmarks else [],
                d.zone_trust_margin + d.zone_landmarks_margin,
                tuple(d.zone_trust_shift),
                d.zone_trust_scale,
            ),
            redundancy=d.redundancy,
            **({"redundancy_gate": chi2_gate(d.redundancy_false_alarm)} if d.redundancy else {}),
            redundancy_min_peers=float(d.redundancy_min_peers),
            redundancy_cap_fusion=d.redundancy_cap_fusion,
            redundancy_sequence=d.redundancy_sequence,
            **(
                {"redundancy_sequence_gate": chi2_gate(d.redundancy_sequence_false_alarm)}
                if d.redundancy_sequence
                else {}
            ),
            redundancy_sequence_hold=float(d.redundancy_sequence_hold),
            redundancy_sequence_forget=float(d.redundancy_sequence_forget),
            reciprocal=d.reciprocal,
            **(
                {
                    "reciprocal_gate": chi2_gate(d.reciprocal_false_alarm, dof=1),
                    "reciprocal_sequence_gate": chi2_gate(d.reciprocal_sequence_false_alarm, dof=1),
                }
                if d.reciprocal
                else {}
            ),
            reciprocal_hold=float(d.reciprocal_hold),
            reciprocal_forget=float(d.reciprocal_forget),
            witness=d.witness,
            witness_liars=float(d.witness_liars),
            witness_k=float(d.witness_k),
            witness_h=float(d.witness_h),
            witness_false_alarm=float(d.witness_false_alarm),
            outvoted=d.outvoted,
            outvoted_cap=float(d.outvoted_cap),
            outvoted_max_std=float(d.outvoted_max_std),
            startup_steps=int(d.startup_steps),
            startup_floor_std=float(d.startup_floor_std),
            startup_decay=float(d.startup_decay),
            startup_claims=bool(d.startup_claims),
            lockout_share=float(d.lockout_share),
            lockout_window=float(d.lockout_window),
            lockout_floor_std=float(d.lockout_floor_std),
        )

    def replace(self, **changes: Any) -> Scenario:
        """Copy with dotted-path changes, validated: ``replace(**{"detector.rho": 0.3})``."""
        # Local imports: the parser and the writer build and read these spec classes, so
        # they import this module; importing them here at module level would be circular.
        from resloc.experiments.config_dump import scenario_to_dict
        from resloc.experiments.config_parse import parse_scenario, set_dotted

        data = scenario_to_dict(self)
        for dotted, value in changes.items():
            set_dotted(data, dotted, value)
        return parse_scenario(data, source="override")


# Tables of the TOML file and where they live in Scenario.
SCENARIO_TABLES: dict[str, tuple[type, tuple[str, ...]]] = {
    "run": (RunSpec, ("run",)),
    "team": (TeamSpec, ("world", "team")),
    "motion": (MotionSpec, ("world", "motion")),
    "sensing": (SensingSpec, ("world", "sensing")),
    "estimator": (EstimatorSpec, ("estimator",)),
    "detector": (DetectorSpec, ("detector",)),
    "trigger": (TriggerSpec, ("trigger",)),
    "attack": (AttackSpec, ("world", "attack")),
}
ZONE_TABLES = ("sdz", "cdz")


def default_scenario() -> Scenario:
    """The embedded default: the paper's 17-robot arc-turn with one SDZ and one CDZ."""
    # Local import, for the reason given in Scenario.replace; default_scenario stays here
    # because the docs import it from this module.
    from resloc.experiments.config_parse import parse_scenario

    text = resources.files("resloc").joinpath("data/default.toml").read_text(encoding="utf-8")
    return parse_scenario(tomllib.loads(text), source="embedded default scenario")
