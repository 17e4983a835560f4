"""Reproduce the paper's "Experiments" section: every experiment over several seeds, the
claims checked against the measurements, and a report (Markdown and HTML).

Every experiment is the embedded default scenario plus a few overrides
(:func:`experiments`), so retuned defaults flow through. Each one is also a scenario or sweep
file under ``examples/paper/`` (:func:`write_examples`), runnable on its own.

Statistics: each experiment runs ``seeds`` Monte Carlo trials (batched in one run). Every
per-seed scalar is summarized by its mean and 95% Student-t interval
(:mod:`resloc.experiments.stats`). Within one seed all filters see identical data, so filter
comparisons use paired per-seed differences. A claim *holds* when its interval lies entirely
on the claimed side, *does not hold* when it lies entirely on the other side, is *not
reproduced* when an equivalence test (TOST) shows the claimed effect absent, and is
*inconclusive* when the interval is too wide to decide. Nothing is tuned to match the paper.

The package by job: :mod:`~resloc.experiments.reproduce.catalogue` (the experiments),
:mod:`~resloc.experiments.reproduce.orchestration` (running and writing),
:mod:`~resloc.experiments.reproduce.claims` (the claims checked),
:mod:`~resloc.experiments.reproduce.evidence` (units and the tests that decide a claim) and
:mod:`~resloc.experiments.reproduce.report` (the report). ``python -m
resloc.experiments.reproduce --write-examples DIR`` rewrites ``examples/paper``.
"""

from resloc.experiments.reproduce.catalogue import (
    FIGURES,
    FULL_SEEDS,
    QUICK_SEEDS,
    QUICK_STEPS,
    SECTIONS,
    Experiment,
    experiments,
    write_examples,
)
from resloc.experiments.reproduce.claims import Claim, evaluate_claims
from resloc.experiments.reproduce.orchestration import (
    Reproduction,
    results_dict,
    run_reproduction,
    write_reproduction,
)
from resloc.experiments.reproduce.report import build_report

__all__ = [
    "FIGURES",
    "FULL_SEEDS",
    "QUICK_SEEDS",
    "QUICK_STEPS",
    "SECTIONS",
    "Claim",
    "Experiment",
    "Reproduction",
    "build_report",
    "evaluate_claims",
    "experiments",
    "results_dict",
    "run_reproduction",
    "write_examples",
    "write_reproduction",
]
