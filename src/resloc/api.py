"""The public API of resloc: what a library user needs, from one place.

Also available at the package top level (``import resloc; resloc.run_scenario(...)``),
imported on first use so that ``import resloc`` stays light.

Scenarios and studies
    :func:`default_scenario`, :func:`load_scenario`, :class:`Scenario` (``.replace`` with
    dotted keys); :func:`run_scenario` -> :class:`RunResult`; :func:`load_sweep`,
    :func:`run_sweep` -> :class:`SweepResult`; :func:`run_mrclam` (UTIAS MRCLAM replay,
    :class:`MRCLAMConfig`) -> :class:`MRCLAMResult`.
The estimator (one robot, batch size 1, or every robot of every trial at once)
    :func:`make_filter` (``"ckf"``, ``"ukf"``, ``"ekf"``), :class:`CLParams`,
    :func:`predict`, :class:`LinkBatch`, :func:`correct` -> :class:`LinkOutcome`,
    :class:`LinkMemory`, and :class:`RobotNode`, one robot's stateful process.
Options
    :class:`FusionMethod` and :func:`fusion_strategy`, :class:`InnovationNorm`; errors
    :class:`ConfigError`, :class:`DataError`, :class:`NumericalError`.
"""

from __future__ import annotations

from resloc.cl.detector import InnovationNorm
from resloc.cl.fusion import FusionMethod
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.links import LinkBatch, LinkOutcome
from resloc.cl.memory import LinkMemory
from resloc.cl.node import RobotNode
from resloc.cl.params import CLParams
from resloc.cl.step import correct, predict
from resloc.errors import ConfigError, DataError, NumericalError
from resloc.experiments.config import Scenario, default_scenario
from resloc.experiments.config_parse import load_scenario
from resloc.experiments.mrclam import MRCLAMConfig, MRCLAMResult, run_mrclam
from resloc.experiments.runner import RunResult, run_scenario
from resloc.experiments.sweep import SweepResult, SweepSpec, load_sweep, run_sweep
from resloc.filters.base import make_filter

__all__ = [
    "CLParams",
    "ConfigError",
    "DataError",
    "FusionMethod",
    "InnovationNorm",
    "LinkBatch",
    "LinkMemory",
    "LinkOutcome",
    "MRCLAMConfig",
    "MRCLAMResult",
    "NumericalError",
    "RobotNode",
    "RunResult",
    "Scenario",
    "SweepResult",
    "SweepSpec",
    "correct",
    "default_scenario",
    "fusion_strategy",
    "load_scenario",
    "load_sweep",
    "make_filter",
    "predict",
    "run_mrclam",
    "run_scenario",
    "run_sweep",
]
