"""Scenario files: schema, strict validation, TOML load/dump, and the embedded default.

A scenario is a TOML file with the tables ``[run]``, ``[team]``, ``[motion]``,
``[sensing]``, ``[estimator]``, ``[detector]``, ``[trigger]``, ``[attack]`` and the arrays of
tables ``[[sdz]]`` and ``[[cdz]]``. Every key is optional (defaults below); an unknown key, a
wrong type or an out-of-range value raises :class:`~resloc.errors.ConfigError` with one line
naming the field, the value and the fix.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import tomllib
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import NORM_GATE, OPTION_CHECKS
from resloc.cl.detection_zone import zone_map
from resloc.cl.detector import InnovationNorm
from resloc.cl.fusion import CICriterion, FusionMethod
from resloc.cl.fusion_methods import FUSION_STRATEGIES, fusion_strategy
from resloc.cl.gauge import GaugeSums
from resloc.cl.graph import Lambda2Source
from resloc.cl.params import CLParams, NeighbourEstimate, ThresholdInnovation, UpdateMode
from resloc.errors import ConfigError
from resloc.filters.base import FilterKind
from resloc.schema import option
from resloc.validation import INT64_MAX, check_one_line_name
from resloc.world.control import LeaderPath
from resloc.world.spec import (
    ARENA_MAX,
    STD_MIN,
    AttackSpec,
    MotionSpec,
    SensingSpec,
    TeamSpec,
    WorldSpec,
    ZoneSpec,
)

__all__ = [
    "DetectorSpec",
    "EstimatorSpec",
    "RiskSource",
    "RunSpec",
    "Scenario",
    "TriggerSpec",
    "build",
    "default_scenario",
    "dump_scenario",
    "load_scenario",
    "parse_scenario",
    "scenario_to_dict",
    "toml_value",
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
        data = scenario_to_dict(self)
        for dotted, value in changes.items():
            set_dotted(data, dotted, value)
        return parse_scenario(data, source="override")


# Sections of the TOML file and where they live in Scenario.
_SECTIONS: dict[str, tuple[type, tuple[str, ...]]] = {
    "run": (RunSpec, ("run",)),
    "team": (TeamSpec, ("world", "team")),
    "motion": (MotionSpec, ("world", "motion")),
    "sensing": (SensingSpec, ("world", "sensing")),
    "estimator": (EstimatorSpec, ("estimator",)),
    "detector": (DetectorSpec, ("detector",)),
    "trigger": (TriggerSpec, ("trigger",)),
    "attack": (AttackSpec, ("world", "attack")),
}
_ZONE_SECTIONS = ("sdz", "cdz")
_LIST_LENGTHS = {
    "motion.odometry_std": 2,
    "motion.process_floor_std": 3,
    "attack.bias": 2,
    "attack.stealth_direction": 2,
    "detector.zone_trust_shift": 2,
    "center": 2,
}


def _type_name(v: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array"}.get(
        type(v), type(v).__name__
    )


def _check_number(path: str, value: Any, meta: dict, want: type) -> float | int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        what = "an integer" if want is int else "a number"
        raise ConfigError(f"{path}: expected {what}, got {_type_name(value)} {value!r}")
    if want is int and not isinstance(value, int):
        raise ConfigError(f"{path}: expected an integer, got {value!r}")
    if isinstance(value, float) and math.isnan(value):
        raise ConfigError(f"{path}: NaN is not allowed")
    if isinstance(value, float) and math.isinf(value):
        raise ConfigError(f"{path}: {value!r} is not allowed; give a finite number")
    why = ""
    if meta.get("min") == STD_MIN:
        why = f" (a zero noise std makes the covariance singular; {STD_MIN:g} is almost noiseless)"
    if "min" in meta and value < meta["min"]:
        raise ConfigError(
            f"{path}: {value!r} is below the minimum {meta['min']}; use >= {meta['min']}{why}"
        )
    if "max" in meta and value > meta["max"]:
        raise ConfigError(
            f"{path}: {value!r} is above the maximum {meta['max']}; use <= {meta['max']}"
        )
    if "gt" in meta and not value > meta["gt"]:
        raise ConfigError(f"{path}: {value!r} must be greater than {meta['gt']}")
    return want(value)


def build(cls: type, data: Any, path: str) -> Any:
    """Build dataclass ``cls`` from a mapping, validating every key (see module doc)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table, got {_type_name(data)} {data!r}")
    names = {f.name: f for f in fields(cls)}
    for key in data:
        if key not in names:
            known = ", ".join(sorted(names))
            raise ConfigError(f"{path}.{key}: unknown key; known keys here: {known}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _convert(f"{path}.{name}", value, hints[name], names[name].metadata)
    return cls(**kwargs)


def _convert(path: str, value: Any, hint: Any, meta: Any) -> Any:
    meta = dict(meta or {})
    if isinstance(hint, type) and issubclass(hint, enum.Enum | FusionMethod):  # names
        choices = [m.value for m in hint]
        if not isinstance(value, str) or value not in choices:
            raise ConfigError(f"{path}: {value!r} is not one of {', '.join(choices)}")
        return hint(value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if hint in (int, float):
        return _check_number(path, value, meta, hint)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {_type_name(value)} {value!r}")
        return value
    if hint is list:
        if not isinstance(value, list):
            raise ConfigError(f"{path}: expected an array, got {_type_name(value)} {value!r}")
        short = (
            path.split(".", 1)[1] if path.count(".") and path.startswith(("sdz", "cdz")) else path
        )
        want_len = _LIST_LENGTHS.get(short.split("[")[0]) or _LIST_LENGTHS.get(
            path.rsplit(".", 1)[-1]
        )
        if want_len is not None:
            if len(value) != want_len:
                raise ConfigError(f"{path}: expected {want_len} numbers, got {value!r}")
            return [_check_number(f"{path}[{k}]", v, meta, float) for k, v in enumerate(value)]
        return list(value)
    if is_dataclass(hint):
        return build(hint, value, path)
    raise ConfigError(f"{path}: unsupported value {value!r}")  # pragma: no cover


def set_dotted(data: dict, dotted: str, value: Any) -> None:
    """Set ``data["a"]["b"] = value`` for ``dotted = "a.b"`` (creating tables)."""
    keys = dotted.split(".")
    node = data
    for k in keys[:-1]:
        node = node.setdefault(k, {})
        if not isinstance(node, dict):
            raise ConfigError(f"{dotted}: {k!r} is not a table")
    node[keys[-1]] = value


def parse_scenario(data: dict, source: str = "scenario") -> Scenario:
    """Validate a scenario mapping (as read from TOML) into a :class:`Scenario`.

    Raises
    ------
    ConfigError
        With one line naming ``source``, the field and the fix.
    """
    try:
        return _parse(data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _parse(data: dict) -> Scenario:
    if not isinstance(data, dict):
        raise ConfigError("expected a TOML document")
    known = set(_SECTIONS) | set(_ZONE_SECTIONS)
    for key in data:
        if key not in known:
            raise ConfigError(f"{key}: unknown section; known sections: {', '.join(sorted(known))}")
    parts: dict[str, Any] = {}
    for section, (cls, _) in _SECTIONS.items():
        parts[section] = build(cls, data.get(section, {}), section)
    zones: dict[str, tuple[ZoneSpec, ...]] = {}
    for section in _ZONE_SECTIONS:
        raw = data.get(section, [])
        if isinstance(raw, dict):
            raw = [raw]
        if not isinstance(raw, list):
            raise ConfigError(f"{section}: expected [[{section}]] tables, got {raw!r}")
        zones[section] = tuple(build(ZoneSpec, z, f"{section}[{k}]") for k, z in enumerate(raw))
    run: RunSpec = parts["run"]
    for k, name in enumerate(run.filters):
        if name not in [f.value for f in FilterKind]:
            raise ConfigError(f"run.filters[{k}]: {name!r} is not one of ckf, ukf, ekf")
    if len(set(run.filters)) != len(run.filters):
        raise ConfigError(f"run.filters: {run.filters!r} lists a filter twice")
    if not run.filters and not run.dead_reckoning:
        raise ConfigError("run.filters: empty and dead_reckoning is false; nothing to run")
    team: TeamSpec = parts["team"]
    if team.robots < 2:
        raise ConfigError(
            f"team.robots: {team.robots} robots cannot localize cooperatively; use >= 2"
        )
    trig: TriggerSpec = parts["trigger"]
    det: DetectorSpec = parts["detector"]
    for stage in OPTION_CHECKS:
        problem = stage.problem(det)
        if problem is not None:
            raise ConfigError(f"detector.{problem}")
    est: EstimatorSpec = parts["estimator"]
    problem = fusion_strategy(est.fusion).problem(est)
    if problem is not None:
        raise ConfigError(f"estimator.fusion: {str(est.fusion)!r} {problem}")
    att: AttackSpec = parts["attack"]
    if not any(abs(v) > 0.0 for v in att.stealth_direction):
        raise ConfigError(
            f"attack.stealth_direction: {att.stealth_direction!r} is zero; give a direction "
            "such as [0.0, 1.0] (bearing)"
        )
    check_one_line_name("run.name", run.name)
    _check_waypoints(parts["motion"].waypoints)
    LeaderPath(parts["motion"].waypoints)  # validates the path
    if run.trials * team.robots > 5_000_000:
        raise ConfigError(
            f"run.trials x team.robots = {run.trials * team.robots} exceeds 5,000,000 robots"
        )
    world = WorldSpec(
        team=team,
        motion=parts["motion"],
        sensing=parts["sensing"],
        attack=parts["attack"],
        sdz=zones["sdz"],
        cdz=zones["cdz"],
    )
    return Scenario(
        run=run,
        world=world,
        estimator=parts["estimator"],
        detector=parts["detector"],
        trigger=trig,
    )


def _check_waypoints(waypoints: list) -> None:
    """Each waypoint is ``"arc"`` or ``[x, y]``: two finite numbers inside the arena."""
    for k, w in enumerate(waypoints):
        path = f"motion.waypoints[{k}]"
        if isinstance(w, str):
            continue  # "arc" and its placement are checked by LeaderPath
        if not isinstance(w, list) or len(w) != 2:
            raise ConfigError(f'{path}: expected [x, y] or "arc", got {w!r}')
        for c, v in enumerate(w):
            _check_number(f"{path}[{c}]", v, {"min": -ARENA_MAX, "max": ARENA_MAX}, float)


def read_toml(path: str | Path, kind: str = "scenario") -> dict:
    """Read a TOML file, mapping every failure to one :class:`ConfigError` line.

    Parameters
    ----------
    path : str or Path
    kind : str
        What the file is, for the message (``scenario``, ``sweep``, ...).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")  # a byte-order mark is not an error
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such {kind} file") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read {kind} file ({exc.__class__.__name__})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file.

    Raises
    ------
    ConfigError
        Missing file, TOML syntax error, or invalid content (one line, names the field).
    """
    return parse_scenario(read_toml(path, "scenario"), source=str(Path(path)))


def _plain(v: Any) -> Any:
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    return v


def scenario_to_dict(s: Scenario) -> dict:
    """The scenario as a TOML-ready mapping (every value explicit)."""
    out: dict[str, Any] = {}
    for section, (_, where) in _SECTIONS.items():
        obj: Any = s
        for attr in where:
            obj = getattr(obj, attr)
        out[section] = {k: _plain(v) for k, v in dataclasses.asdict(obj).items()}
    for section in _ZONE_SECTIONS:
        zs = getattr(s.world, section)
        if zs:
            out[section] = [{k: _plain(v) for k, v in dataclasses.asdict(z).items()} for z in zs]
    return out


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        # JSON's string escapes (\n, \t, \", \\, \uXXXX) are TOML's basic-string escapes.
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")  # pragma: no cover


def _toml_table(header: str, values: dict, cls: type) -> list[str]:
    docs = {f.name: f.metadata.get("doc", "") for f in fields(cls)}
    lines = [header]
    for key, val in values.items():
        text = f"{key} = {toml_value(val)}"
        doc = docs.get(key, "")
        lines.append(f"{text:<40} # {doc}" if doc else text)
    return lines


def dump_scenario(s: Scenario) -> str:
    """The scenario as commented TOML text (loads back to an equal scenario)."""
    data = scenario_to_dict(s)
    lines: list[str] = []
    for section, (cls, _) in _SECTIONS.items():
        lines += _toml_table(f"[{section}]", data[section], cls)
        lines.append("")
    for section in _ZONE_SECTIONS:
        for zone in data.get(section, []):
            lines += _toml_table(f"[[{section}]]", zone, ZoneSpec)
            lines.append("")
    return "\n".join(lines)


def default_scenario() -> Scenario:
    """The embedded default: the paper's 17-robot arc-turn with one SDZ and one CDZ."""
    text = resources.files("resloc").joinpath("data/default.toml").read_text(encoding="utf-8")
    return parse_scenario(tomllib.loads(text), source="embedded default scenario")
