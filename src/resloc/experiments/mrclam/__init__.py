"""Replay an MRCLAM dataset through the CL estimators (the same per-robot code and the same
estimator loop as the simulator) and score them against the motion-capture ground truth.

One job per module: ``config`` (:class:`MRCLAMConfig`), ``replay`` (steps of ``dt``, ground
truth at the step times, sightings assigned to steps, zones and the seeded attack draws),
``noise`` (noise fit against ground truth, range-noise levels), ``scoring`` (metrics and
result types), ``run`` (:func:`run_mrclam`: the replay as a step source of
:func:`~resloc.experiments.lockstep.run_lockstep`), ``output`` (:func:`save_mrclam`).
``docs/mrclam.md`` gives the method and the reasons.
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
