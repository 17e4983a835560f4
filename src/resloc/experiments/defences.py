"""The defences, declared once: name -> dotted scenario overrides.

Each defence is a detector configuration of the scenario (``[detector]`` keys, see
:mod:`resloc.cl.detection` for the stages). The adversary suite (``resloc attack``) and the
evaluation in ``docs/beyond.md`` ("Defences") read this mapping; adding a defence is one
entry here. The overrides apply on top of any scenario with
``Scenario.replace(**DEFENCES[name])``.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

from resloc.errors import ConfigError

__all__ = ["DEFENCES", "defence_overrides"]

_NIS = {"detector.enabled": True, "detector.norm": "nis", "detector.false_alarm": 1e-3}
_LINK_CUSUMS = {"detector.cusum": True, "detector.mean_cusum": True}
# The adversary study's table (docs/beyond.md section 6): a looser gate (1% false alarms)
# with the sequence tests added one at a time, with naive and gauge fusion (gauge changes
# only the covariances: its estimates are naive fusion's).
_NIS_STUDY = {"detector.enabled": True, "detector.norm": "nis", "detector.false_alarm": 0.01}
_CUSUM = {**_NIS_STUDY, "detector.cusum": True}
_MEAN = {**_CUSUM, "detector.mean_cusum": True}
_GAUGE = {"estimator.fusion": "gauge"}
_PAPER = {"detector.enabled": True, "detector.norm": "euclidean"}
_FULL = {**_NIS, **_LINK_CUSUMS, "detector.robot_cusum": True, "detector.recovery": True}
_ZONE = {"detector.zone_trust": True}
_REDUNDANCY = {"detector.redundancy": True}
_SEQUENCE = {**_REDUNDANCY, "detector.redundancy_sequence": True}
_RECIPROCAL = {"detector.reciprocal": True}

#: Defence name -> dotted scenario overrides (read-only).
DEFENCES: MappingProxyType[str, MappingProxyType[str, Any]] = MappingProxyType(
    {
        name: MappingProxyType(overrides)
        for name, overrides in {
            # The paper's detector: raw ||Lambda|| > rho (the scenario's rho).
            "paper": dict(_PAPER),
            # Chi-square gate on the NIS (false-alarm probability 0.01 per measurement), then
            # the per-link CUSUM of the NIS, then the signed (mean-shift) CUSUMs.
            "nis": dict(_NIS_STUDY),
            "nis+cusum": dict(_CUSUM),
            "nis+cusum+mean": dict(_MEAN),
            "gauge+paper": {**_GAUGE, **_PAPER},
            "gauge+nis": {**_GAUGE, **_NIS_STUDY},
            "gauge+nis+cusum": {**_GAUGE, **_CUSUM},
            "gauge+nis+cusum+mean": {**_GAUGE, **_MEAN},
            # The stricter gate (false-alarm probability 1e-3) the defences below build on.
            "nis_strict": dict(_NIS),
            # NIS gate + recovery after rejection runs (never locks a robot out).
            "nis_recovery": {**_NIS, "detector.recovery": True},
            # NIS gate + per-link sequence tests (CUSUM of the NIS, signed CUSUMs).
            "nis_link_cusums": {**_NIS, **_LINK_CUSUMS},
            # + the per-robot CUSUM of the NIS over all of a robot's links.
            "nis_link_robot_cusums": {**_NIS, **_LINK_CUSUMS, "detector.robot_cusum": True},
            # Everything: gate, per-link and per-robot sequence tests, recovery.
            "full": dict(_FULL),
            # Zone-aware trust (cl/detection_zone.py): a robot does not fuse what its own
            # sensor reports while its estimate is inside a mapped SDZ. Legitimate only under
            # the paper's threat model (sensing attacks confined to the known SDZs); the
            # '@shifted' / '@shrunk' variants give the robots a wrong map (centre moved by
            # one radius; radius halved) to measure what is left when that model fails.
            "zone": {**_NIS, **_ZONE},
            "zone+full": {**_FULL, **_ZONE},
            "zone+full@shifted": {**_FULL, **_ZONE, "detector.zone_trust_shift": [0.5, 0.0]},
            "zone+full@shrunk": {**_FULL, **_ZONE, "detector.zone_trust_scale": 0.5},
            # Redundancy (cl/detection_redundancy.py): a link whose fix of the robot's
            # position disagrees with its other neighbours' fixes is not fused, claimed
            # covariances capped at a typical neighbour's. Needs no map.
            "full+redundancy": {**_FULL, **_REDUNDANCY},
            "zone+full+redundancy": {**_FULL, **_ZONE, **_REDUNDANCY},
            # + the sequence test on each link's redundancy residuals over time
            # (cl/detection_sequence.py): a neighbour whose fixes lead the others a little
            # every step accumulates evidence and is held out for a while.
            "full+redundancy+sequence": {**_FULL, **_SEQUENCE},
            "zone+full+redundancy+sequence": {**_FULL, **_ZONE, **_SEQUENCE},
            # + the reciprocal range check (cl/detection_reciprocal.py): the two ends of a
            # pair must agree on their distance, one step and in sum (a flagged link is
            # held out a while, then re-admitted).
            "full+reciprocal": {**_FULL, **_RECIPROCAL},
            "full+redundancy+sequence+reciprocal": {**_FULL, **_SEQUENCE, **_RECIPROCAL},
            "zone+full+redundancy+sequence+reciprocal": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                **_RECIPROCAL,
            },
            # + a robot inside the map is a weak landmark (cl/detection_landmark.py): its
            # estimate there is built from its partners' fixes, and a compromised robot
            # inside closes that loop with its lies.
            "zone+full+redundancy+sequence+cap+landmarks": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
            },
            # + the observers of each robot compare notes on it (cl/detection_witness.py):
            # a per-robot sequence test across observers, robust to f lying ones.
            "zone+full+redundancy+sequence+cap+landmarks+witness": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
                "detector.witness": True,
            },
            # + a robot the notes on itself outvote widens its covariance
            # (cl/detection_outvoted.py).
            "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
                "detector.witness": True,
                "detector.outvoted": True,
            },
            # + no robot's covariance shrinks below 10 mm in its first 10 corrections
            # (cl/detection_startup.py; liars that wait out the 10 steps beat it,
            # docs/attack/startup.md).
            "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
                "detector.witness": True,
                "detector.outvoted": True,
                "detector.startup_steps": 10,
                "detector.startup_floor_std": 0.01,
            },
            # + the floor held for 5 corrections, then decaying by 0.8 a correction (no cliff
            # the liars can time: docs/attack/startup.md section 5).
            "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
                "detector.witness": True,
                "detector.outvoted": True,
                "detector.startup_steps": 5,
                "detector.startup_floor_std": 0.01,
                "detector.startup_decay": 0.8,
            },
            # + a robot whose detector discards most of its links over its last ten
            # corrections raises its covariance to 10 mm (cl/detection_lockout.py: the
            # mid-run partial lock-out, docs/attack/lockout.md).
            "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay+lockout": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
                "detector.zone_landmarks": True,
                "detector.witness": True,
                "detector.outvoted": True,
                "detector.startup_steps": 5,
                "detector.startup_floor_std": 0.01,
                "detector.startup_decay": 0.8,
                "detector.lockout_share": 0.5,
                "detector.lockout_window": 10.0,
                "detector.lockout_floor_std": 0.01,
            },
            # + each neighbour fused with its claimed covariance capped as the test caps it.
            "zone+full+redundancy+sequence+cap": {
                **_FULL,
                **_ZONE,
                **_SEQUENCE,
                "detector.redundancy_cap_fusion": True,
            },
        }.items()
    }
)


def defence_overrides(name: str) -> dict[str, Any]:
    """The overrides of defence ``name`` (a copy).

    Raises
    ------
    ConfigError
        Unknown name (one line listing the known ones).
    """
    try:
        return dict(DEFENCES[name])
    except KeyError:
        raise ConfigError(
            f"defence {name!r} is unknown; known defences: {', '.join(DEFENCES)}"
        ) from None
