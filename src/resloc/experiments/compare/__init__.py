"""resloc's fixes measured against the paper's method (``resloc compare``; the methods are
described in ``docs/beyond.md``). Four studies over seeds, each cell one run with the seeds
as trials (common random numbers across methods): method x scenario (clean, SDZ fixed and
stealthy, CDZ, extra attacks), fusion consistency (NEES against its chi-square band), the
closed-loop detector ROC, and lambda2 with team size.

One module per job: :mod:`~resloc.experiments.compare.methods` (the catalogue),
:mod:`~resloc.experiments.compare.run` (the cells on the study executor),
:mod:`~resloc.experiments.compare.report` (result, targets, Markdown, files); the ROC figure
is :func:`resloc.experiments.plots.compare.plot_roc`.
"""

from resloc.experiments.compare.methods import (
    BEST,
    EXTRA_SCENARIOS,
    METHODS,
    NAIVE_REFERENCE,
    PAPER,
    SCENARIOS,
    study_scenario,
)
from resloc.experiments.compare.report import CompareResult, nees_band, save_compare
from resloc.experiments.compare.run import run_compare

__all__ = [
    "BEST",
    "EXTRA_SCENARIOS",
    "METHODS",
    "NAIVE_REFERENCE",
    "PAPER",
    "SCENARIOS",
    "CompareResult",
    "nees_band",
    "run_compare",
    "save_compare",
    "study_scenario",
]
