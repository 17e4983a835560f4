"""resloc's fixes measured against the paper's method (``resloc compare``).

Four studies, each over seeds (Monte Carlo trials batched in one run per cell, common
random numbers across methods):

* **main table**: method x scenario (clean, SDZ fixed bias, SDZ stealthy, CDZ jamming) ->
  MSLE, RMSE, NEES, communication rate, detection TPR / FPR, means with 95% Student-t
  intervals over seeds; plus extra attacks (replay, a stealthy attacker that only knows the
  per-measurement gate);
* **fusion consistency** on the default scenario: naive, CI, split CI, factorized, tracked,
  gauge, with the NEES chi-square band;
* **detector ROC** (closed loop): raw-norm and NIS gates swept over their thresholds
  (one threshold per trial of one run, the attacker adapting to each) under fixed and
  stealthy attacks;
* **lambda2 with N**: the distributed estimate's error against the true algebraic
  connectivity, and the trigger's communication rate with the global and the distributed
  value, for growing teams.

One module per job: :mod:`~resloc.experiments.compare.methods` (the catalogue),
:mod:`~resloc.experiments.compare.run` (the cells on the study executor),
:mod:`~resloc.experiments.compare.report` (result, targets, Markdown, files); the ROC figure
is :func:`resloc.experiments.plots.compare.plot_roc`. ``docs/beyond.md`` describes the methods.
"""

from resloc.experiments.compare.methods import (
    BEST,
    DEFAULT,
    EXTRA_SCENARIOS,
    FUSION_METHODS,
    METHODS,
    NAIVE_REFERENCE,
    PAPER,
    ROC_GATES,
    SCENARIOS,
    Method,
    RocGate,
    StudyScenario,
    study_scenario,
)
from resloc.experiments.compare.report import CompareResult, nees_band, save_compare
from resloc.experiments.compare.run import run_compare

__all__ = [
    "BEST",
    "DEFAULT",
    "EXTRA_SCENARIOS",
    "FUSION_METHODS",
    "METHODS",
    "NAIVE_REFERENCE",
    "PAPER",
    "ROC_GATES",
    "SCENARIOS",
    "CompareResult",
    "Method",
    "RocGate",
    "StudyScenario",
    "nees_band",
    "run_compare",
    "save_compare",
    "study_scenario",
]
