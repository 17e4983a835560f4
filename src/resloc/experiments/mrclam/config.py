"""The configuration of an MRCLAM replay: every option besides the data, validated on
construction, and the per-robot estimator parameters it implies."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import CHI_SQUARE_NORMS
from resloc.cl.params import CLParams
from resloc.errors import ConfigError
from resloc.filters.base import FilterKind
from resloc.innovation_norm import InnovationNorm
from resloc.validation import check_finite, check_seed
from resloc.world.attacks import AttackKind, LinkScope

__all__ = ["MAX_DURATION", "MAX_REPLAY_STEPS", "MIN_DT", "MRCLAMConfig", "default_rho"]

#: Smallest replay step (s): the odometry runs at ~67 Hz and the ground truth at 100 Hz, so a
#: step below a millisecond replays no new data, only more memory.
MIN_DT = 1e-3
#: Upper bounds of the float options (all >= 0; positivity rules are in ``__post_init__``).
_FLOAT_BOUNDS = {
    "range_std": 1e3,
    "range_std_rel": 1e3,
    "bearing_std": 2 * math.pi,
    "rho": 1e6,
    "alpha": 1e6,
    "gamma": 1e6,
    "zeta_s": 1e3,
    "zeta_c": 1e3,
    "gt_max_gap": 1e3,
    "link_fraction": 1.0,
}
#: Longest ``duration`` (s): the MRCLAM datasets last 15 to 45 minutes.
MAX_DURATION = 1e6
#: Longest replay in steps (the same bound as a scenario's ``run.steps``).
MAX_REPLAY_STEPS = 10_000_000


@dataclass(frozen=True)
class MRCLAMConfig:
    """Everything a replay needs besides the data. Validated on construction.

    Attributes
    ----------
    filters : tuple of str
        Estimators to run (``ckf``, ``ukf``, ``ekf``); dead reckoning always runs.
    dt : float
        Step (s).
    duration : float or None
        Replay only the first ``duration`` seconds (None: all).
    landmarks : bool
        Fuse landmark sightings as absolute anchors.
    zones : bool
        Apply the attack layer (SDZ falsification, CDZ jamming).
    sdz, cdz : tuple (x, y, radius) or None
        Zone discs (m); None places them automatically (:func:`default_zones`).
    seed : int
        Seed of the attack and channel draws.
    range_std, range_std_rel, bearing_std : float
        Measurement noise of ``R``: range std ``sqrt(range_std^2 + (range_std_rel z)^2)``
        (m; grows with the measured range ``z``), bearing std (rad). Defaults: fitted to the
        robust (MAD) spread of measured minus ground-truth range/bearing on Dataset 6.
    odometry_density : tuple of float
        Odometry noise densities ``(m/s sqrt(s), rad/s sqrt(s))``: the std of the distance and
        heading error accumulated in 1 s. Per step the filter uses ``density / sqrt(dt)`` as
        ``CLParams.odometry_std``, so results do not depend on ``dt`` through the noise.
    init_std : tuple of float
        Initial position (m) and heading (rad) standard deviations around the first
        ground-truth sample.
    detector : bool
    rho : float or None
        Detection threshold, in the units of ``detector_norm``. None: the norm's default,
        ``sqrt(chi2.ppf(1 - 1e-3, 2))`` for ``nis`` (a chi-square gate at false-alarm
        probability 1e-3), 1.0 for the raw norms (the threshold tuned on Dataset 6).
    detector_norm : InnovationNorm
        Default ``nis``: the NIS gate scales with the robot's own covariance, so it was not
        tuned to one dataset (the paper's raw ``euclidean`` norm is ``paper_detector()``).
    recovery : bool
        Detector recovery after rejection runs (:mod:`resloc.cl.detection_recovery`): a
        robot whose measurements are all rejected ``recovery_after`` times in a row has them
        re-admitted through an inflated NIS gate. On by default: a robot is never locked out.
    recovery_after : int
        Consecutive rejected measurements of one robot before recovery.
    trigger : bool
    alpha, gamma, zeta_s, zeta_c : float
        Event-threshold constants of eq. (11).
    attack_kind : AttackKind
    attack_bias : tuple of float
        Injection magnitude ``[range (m), bearing (rad)]``.
    attack_links : LinkScope
    link_fraction : float
    gt_max_gap : float
        Ground-truth gaps longer than this (s) are not scored.
    strict : bool
        Fail on any data row that is reordered, repeated or unusable instead of counting
        it (:func:`~resloc.datasets.mrclam.load_mrclam`).
    """

    filters: tuple[str, ...] = ("ckf", "ukf", "ekf")
    dt: float = 0.02
    duration: float | None = None
    landmarks: bool = True
    zones: bool = False
    sdz: tuple[float, float, float] | None = None
    cdz: tuple[float, float, float] | None = None
    seed: int = 0
    range_std: float = 0.03
    range_std_rel: float = 0.07
    bearing_std: float = 0.015
    odometry_density: tuple[float, float] = (0.015, 0.04)
    init_std: tuple[float, float] = (0.02, 0.02)
    detector: bool = True
    rho: float | None = None
    detector_norm: InnovationNorm = InnovationNorm.NIS
    recovery: bool = True
    recovery_after: int = 10
    trigger: bool = True
    alpha: float = 0.3
    gamma: float = 0.5
    zeta_s: float = 0.5
    zeta_c: float = 0.5
    attack_kind: AttackKind = AttackKind.RANDOM
    attack_bias: tuple[float, float] = (0.4, 0.8)
    attack_links: LinkScope = LinkScope.FULL
    link_fraction: float = 0.5
    gt_max_gap: float = 0.25
    strict: bool = False

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "detector_norm", InnovationNorm(self.detector_norm))
        except ValueError:
            raise ConfigError(
                f"detector_norm must be one of euclidean, scaled, nis, got {self.detector_norm!r}"
            ) from None
        if self.rho is None:
            object.__setattr__(self, "rho", default_rho(self.detector_norm))
        if isinstance(self.recovery_after, bool) or not (
            isinstance(self.recovery_after, int) and self.recovery_after >= 1
        ):
            raise ConfigError(
                f"recovery_after must be an integer >= 1, got {self.recovery_after!r}"
            )
        for name in self.filters:
            if name not in {k.value for k in FilterKind}:
                raise ConfigError(f"filters: unknown filter {name!r}; use ckf, ukf or ekf")
        # Finite, physical ranges first (resloc.validation); the rules below add relations.
        check_finite("dt", self.dt, MIN_DT, 1.0, unit=" s")
        check_seed("seed", self.seed)
        for name, hi in _FLOAT_BOUNDS.items():
            check_finite(name, getattr(self, name), 0.0, hi)
        for name in ("odometry_density", "init_std", "attack_bias"):
            for k, v in enumerate(getattr(self, name)):
                check_finite(f"{name}[{k}]", v, 0.0, 1e3)
        for name in ("sdz", "cdz"):
            for k, v in enumerate(getattr(self, name) or ()):
                check_finite(f"{name}[{k}]", v, -1e4, 1e4)
        # Relations and positivity the ranges above do not express.
        for name in ("range_std", "bearing_std", "rho", "gt_max_gap"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be a positive number, got {getattr(self, name)}")
        if self.duration is not None:
            check_finite("duration", self.duration, 0.0, MAX_DURATION, lo_open=True, unit=" s")
        for name in ("odometry_density", "init_std", "attack_bias"):
            if len(v := getattr(self, name)) != 2:
                raise ConfigError(f"{name} must be two non-negative numbers, got {v}")
        for name in ("sdz", "cdz"):
            z = getattr(self, name)
            if z is not None and (len(z) != 3 or not z[2] > 0):
                raise ConfigError(f"{name} must be (x, y, radius) with radius > 0, got {z}")
        if (self.sdz is not None or self.cdz is not None) and not self.zones:
            raise ConfigError("sdz/cdz given but the attack layer is off; also pass --zones")

    def cl_params(self) -> CLParams:
        """The per-robot estimator parameters for robot-to-robot links."""
        dens = np.asarray(self.odometry_density, float)
        return CLParams(
            range_std=self.range_std,
            bearing_std=self.bearing_std,
            odometry_std=tuple((dens / np.sqrt(self.dt)).tolist()),
            detector=self.detector,
            rho=self.rho,
            detector_norm=self.detector_norm,
            recovery=self.detector and self.recovery,
            recovery_after=float(self.recovery_after),
            trigger=self.trigger,
            alpha=self.alpha,
            gamma=self.gamma,
            zeta_s=self.zeta_s,
            zeta_c=self.zeta_c,
            trigger_norm=InnovationNorm.EUCLIDEAN,
        )

    def paper_detector(self) -> MRCLAMConfig:
        """This configuration with the paper's detector: the raw-norm gate ``||Lambda|| >
        rho`` at ``rho = 1`` (tuned on Dataset 6), no recovery."""
        return dataclasses.replace(
            self, detector_norm=InnovationNorm.EUCLIDEAN, rho=1.0, recovery=False
        )

    def to_dict(self) -> dict:
        """Plain-value dict (for ``summary.json``)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out


#: False-alarm probability of the default NIS gate of a replay.
DEFAULT_FALSE_ALARM = 1e-3


def default_rho(norm: InnovationNorm) -> float:
    """The default detection threshold of a replay for detector norm ``norm``."""
    norm = InnovationNorm(norm)
    if norm in CHI_SQUARE_NORMS:
        return math.sqrt(chi2_gate(DEFAULT_FALSE_ALARM))
    return 1.0
