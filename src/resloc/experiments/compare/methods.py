"""The catalogue of ``resloc compare``: the compared methods, the scenarios, the ROC gates,
and the validated scenario of one cell."""

from __future__ import annotations

from dataclasses import dataclass, field

from resloc.experiments.config import Scenario, default_scenario

__all__ = [
    "BEST",
    "DEFAULT",
    "EXTRA_SCENARIOS",
    "FUSION_METHODS",
    "METHODS",
    "NAIVE_REFERENCE",
    "PAPER",
    "QUICK_TEAM_SIZES",
    "ROC_GATES",
    "SCENARIOS",
    "TEAM_SIZES",
    "Method",
    "RocGate",
    "StudyScenario",
    "study_scenario",
]


@dataclass(frozen=True)
class Method:
    """An estimator configuration: dotted scenario changes on top of the paper's."""

    key: str
    label: str
    changes: dict = field(default_factory=dict)


_NIS = {"detector.norm": "nis", "detector.false_alarm": 0.01}

_NIS_CUSUM = {**_NIS, "detector.cusum": True}
_MEAN = {"detector.mean_cusum": True}


def _fusion(method: str, *options: dict) -> dict:
    """The changes that select fusion ``method``, then ``options`` (dotted changes)."""
    return {"estimator.fusion": method, **{k: v for o in options for k, v in o.items()}}


#: The main table's methods (the paper first).
METHODS: tuple[Method, ...] = (
    Method("paper", "paper: naive fusion, raw-norm gate", {}),
    Method("ci", "CI fusion, raw-norm gate", _fusion("ci")),
    Method("tracked+nis+cusum", "tracked, NIS gate + CUSUM", _fusion("tracked", _NIS_CUSUM)),
    Method("gauge+nis", "gauge, NIS gate", _fusion("gauge", _NIS)),
    Method("gauge+nis+cusum", "gauge, NIS gate + CUSUM", _fusion("gauge", _NIS_CUSUM)),
    Method(
        "gauge+nis+cusum+mean",
        "gauge, NIS gate + CUSUM + mean-shift CUSUM",
        _fusion("gauge", _NIS_CUSUM, _MEAN),
    ),
)

#: The fusion-consistency table's methods: each fusion with the unit-aware detector (the
#: default scenario's random injections pass the raw-norm gate and would corrupt any fusion),
#: plus the paper's configuration and tracked fusion with the paper's gate for reference.
#: Each "+nis+cusum" row is compared with naive fusion under the same detector.
FUSION_METHODS: tuple[Method, ...] = (
    Method("naive", "naive, raw-norm gate (paper)", {}),
    Method("naive+nis+cusum", "naive, NIS gate + CUSUM", dict(_NIS_CUSUM)),
    Method("ci+nis+cusum", "CI, NIS gate + CUSUM", _fusion("ci", _NIS_CUSUM)),
    Method("split_ci+nis+cusum", "split CI, NIS gate + CUSUM", _fusion("split_ci", _NIS_CUSUM)),
    Method(
        "factorized+nis+cusum",
        "factorized (Luft et al.), NIS gate + CUSUM",
        _fusion("factorized", _NIS_CUSUM),
    ),
    Method("tracked", "tracked, raw-norm gate", _fusion("tracked")),
    Method("tracked+nis+cusum", "tracked, NIS gate + CUSUM", _fusion("tracked", _NIS_CUSUM)),
    Method("gauge+nis+cusum", "gauge, NIS gate + CUSUM", _fusion("gauge", _NIS_CUSUM)),
    Method(
        "gauge(consensus)+nis+cusum",
        "gauge with consensus sums, NIS gate + CUSUM",
        _fusion("gauge", {"estimator.gauge_sums": "consensus"}, _NIS_CUSUM),
    ),
    Method(
        "gauge+nis+cusum+mean",
        "gauge, NIS gate + CUSUM + mean-shift CUSUM",
        _fusion("gauge", _NIS_CUSUM, _MEAN),
    ),
)

#: The naive reference of the fusion target (same detector as the methods it is compared to).
NAIVE_REFERENCE = "naive+nis+cusum"


@dataclass(frozen=True)
class StudyScenario:
    """A scenario of the study: dotted changes on the embedded default."""

    key: str
    label: str
    changes: dict


_SDZ = {"center": [0.45, -0.55], "radius": 0.5, "peak": 0.9}
_CDZ = {"center": [0.2, 0.45], "radius": 0.4, "peak": 1.0}
#: In --quick runs (200 steps) the zones sit where the team is during its first 200 steps.
_QUICK_ZONE = {"center": [-0.55, -0.9], "radius": 0.5, "peak": 0.9}
_BIAS = [0.3, 0.6]

#: The main table's scenarios.
SCENARIOS: tuple[StudyScenario, ...] = (
    StudyScenario("clean", "clean (no zones)", {"sdz": [], "cdz": []}),
    StudyScenario(
        "sdz_fixed",
        "SDZ, fixed bias",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "fixed", "attack.bias": _BIAS},
    ),
    StudyScenario(
        "sdz_stealthy",
        "SDZ, stealthy",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "stealthy", "attack.bias": _BIAS},
    ),
    StudyScenario("cdz_jamming", "CDZ jamming", {"sdz": [], "cdz": [_CDZ]}),
)

#: Further attacks, for the paper's method and the best combination.
EXTRA_SCENARIOS: tuple[StudyScenario, ...] = (
    StudyScenario(
        "sdz_stealthy_gate",
        "SDZ, stealthy (knows the gate only)",
        {
            "sdz": [_SDZ],
            "cdz": [],
            "attack.kind": "stealthy",
            "attack.bias": _BIAS,
            "attack.stealth_knowledge": "gate",
        },
    ),
    StudyScenario(
        "sdz_replay",
        "SDZ, replay (2 s old)",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "replay", "attack.replay_delay": 60},
    ),
)

#: The paper's default scenario (SDZ with random injections + CDZ), for fusion consistency.
DEFAULT = StudyScenario("default", "default (SDZ random + CDZ)", {})

#: The best combination (the target's subject) and its reference.
BEST = "gauge+nis+cusum+mean"
PAPER = "paper"


@dataclass(frozen=True)
class RocGate:
    """A gate of the detector ROC: the scenario changes that select it and the detector
    option swept, whose values are listed strictest first (most discards)."""

    key: str
    changes: dict
    option: str
    threshold_name: str
    values: tuple[float, ...]


#: ROC sweeps: raw-norm thresholds rho, NIS gate false-alarm probabilities.
ROC_GATES: tuple[RocGate, ...] = (
    RocGate("raw-norm", {}, "rho", "rho", (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.5)),
    RocGate(
        "nis",
        {"detector.norm": "nis"},
        "false_alarm",
        "p_fa",
        (0.3, 0.1, 0.03, 0.01, 1e-3, 1e-4, 1e-6),
    ),
)

#: Team sizes of the lambda2 study.
TEAM_SIZES = (5, 10, 17, 26, 36)
QUICK_TEAM_SIZES = (5, 17)


def _quick_changes(changes: dict) -> dict:
    out = dict(changes)
    for key in ("sdz", "cdz"):
        if out.get(key):
            out[key] = [_QUICK_ZONE]
    return out


def study_scenario(
    scenario: StudyScenario,
    method: Method,
    seeds: int,
    steps: int,
    filt: str = "ckf",
    quick: bool = False,
    seed: int = 0,
    robots: int | None = None,
) -> Scenario:
    """The validated :class:`Scenario` of one cell (all seeds as trials of one run)."""
    changes = _quick_changes(scenario.changes) if quick else dict(scenario.changes)
    extra = {} if robots is None else {"team.robots": int(robots)}
    return default_scenario().replace(
        **changes,
        **method.changes,
        **{
            "run.name": f"{scenario.key} / {method.key}",
            "run.trials": int(seeds),
            "run.steps": int(steps),
            "run.seed": int(seed),
            "run.filters": [filt],
            "run.dead_reckoning": False,
            **extra,
        },
    )
