"""Replay an MRCLAM dataset through the CL estimators (the same per-robot code and the same
estimator loop as in simulation) and score them against the motion-capture ground truth.

Method (``docs/mrclam.md`` gives the reasons):

* Time is cut into steps of ``dt`` from the dataset start ``t = 0``
  (:mod:`~resloc.experiments.mrclam.replay`). Over step ``(t_{k-1}, t_k]`` every robot
  predicts with the time average of its zero-order-held odometry command over the step
  (exact for the heading change; a robot is at rest before its first odometry row).
* The measurements time-stamped in the step are then fused, sorted by observer and time:
  landmark sightings as fixed neighbours, then robot-to-robot measurements through
  detector, event trigger and channel, in groups of one range-noise level
  (:mod:`~resloc.experiments.mrclam.steps`, :mod:`~resloc.experiments.mrclam.noise`).
  Every estimator runs in :func:`~resloc.experiments.lockstep.run_lockstep`, the loop of
  :func:`~resloc.experiments.runner.run_scenario`: each step timed, a diverging estimator
  stopped and reported while the others finish.
* Adversarial zones (optional): an SDZ falsifies a robot-to-robot measurement with
  probability ``Ds(i)`` at the observer's true position (eq. 5), a CDZ drops the
  transmission with probability ``Dc(i)``, drawn once from seeded streams before the
  estimators run.
* Dead reckoning is the same ``predict`` with no update (EKF moments), the floor.
* Scoring (:mod:`~resloc.experiments.mrclam.scoring`): position RMSE, heading RMSE, NEES
  where the robot's ground truth is valid; MSLE where every robot's is; communication rate.

Modules: ``config`` (:class:`MRCLAMConfig`), ``replay`` (steps, ground truth, zones, attack
draws), ``noise`` (noise fit, range-noise levels), ``steps`` (the replay as a step source),
``scoring`` (metrics, result types), ``run`` (:func:`run_mrclam`), ``output``
(:func:`save_mrclam`).
"""

from __future__ import annotations

from resloc.experiments.lockstep import DEAD_RECKONING
from resloc.experiments.mrclam.config import MRCLAMConfig, default_rho
from resloc.experiments.mrclam.noise import (
    estimate_noise,
    level_groups,
    noise_from_fit,
    range_noise_level,
    range_noise_std,
)
from resloc.experiments.mrclam.output import save_mrclam
from resloc.experiments.mrclam.replay import (
    Replay,
    default_zones,
    ground_truth_at,
    prepare_replay,
    step_commands,
)
from resloc.experiments.mrclam.run import replay_result, run_mrclam
from resloc.experiments.mrclam.scoring import (
    MRCLAMEstimate,
    MRCLAMResult,
    empty_link_log,
    score_estimate,
)

__all__ = [
    "DEAD_RECKONING",
    "MRCLAMConfig",
    "MRCLAMEstimate",
    "MRCLAMResult",
    "Replay",
    "default_rho",
    "default_zones",
    "empty_link_log",
    "estimate_noise",
    "ground_truth_at",
    "level_groups",
    "noise_from_fit",
    "prepare_replay",
    "range_noise_level",
    "range_noise_std",
    "replay_result",
    "run_mrclam",
    "save_mrclam",
    "score_estimate",
    "step_commands",
]
