"""Small run directories shared by the export tests (``tests/test_export_*.py``)."""

from __future__ import annotations

from pathlib import Path

from resloc.experiments.config import default_scenario
from resloc.experiments.mrclam import MRCLAMConfig, run_mrclam, save_mrclam
from resloc.experiments.run_files import save_run
from resloc.experiments.runner import run_scenario

MRCLAM_FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
#: The default team reaches the SDZ (detector rejections) after about 210 steps.
RUN_STEPS = 260


def make_run_dir(out: Path, steps: int = RUN_STEPS, filters=("ckf", "ekf")) -> Path:
    """``resloc run`` output (no plots) of the default scenario cut to ``steps``."""
    sc = default_scenario().replace(**{"run.steps": steps, "run.filters": list(filters)})
    save_run(run_scenario(sc), out, plots=False)
    return out


def make_mrclam_dir(out: Path, duration: float = 20.0) -> Path:
    """``resloc mrclam`` output (no plots) of the shipped excerpt, with danger zones."""
    config = MRCLAMConfig(filters=("ckf",), zones=True, duration=duration, seed=3)
    save_mrclam(run_mrclam(MRCLAM_FIXTURE, config), out, plots=False)
    return out
