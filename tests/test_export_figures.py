"""Figures that tell the truth: the transmission raster shows each robot's share of links,
estimator curves are distinguishable, every panel's axes hold every curve drawn in it,
constrained layout, and one plotting package."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import resloc.experiments.mrclam as mrclam_module
import resloc.experiments.report as report_module
from export_helpers import MRCLAM_FIXTURE
from resloc.experiments import plots
from resloc.experiments.config import default_scenario
from resloc.experiments.mrclam import MRCLAMConfig, run_mrclam
from resloc.experiments.plots import core, link_rates
from resloc.experiments.runner import run_scenario

pytest.importorskip("matplotlib")


@pytest.fixture(scope="module")
def run():
    sc = default_scenario().replace(**{"run.steps": 150, "run.filters": ["ckf", "ukf", "ekf"]})
    return run_scenario(sc)


@pytest.fixture
def captured(monkeypatch):
    """Figures handed to ``save`` (kept open so tests can inspect them)."""
    figs = []

    def keep(plt, fig, path, dpi=core.DPI):
        fig.savefig(path, dpi=dpi)
        figs.append(fig)
        return Path(path)

    for module in ("run", "mrclam", "bands"):
        monkeypatch.setattr(f"resloc.experiments.plots.{module}.save", keep)
    yield figs
    plt = core.pyplot()
    for fig in figs:
        plt.close(fig)


def lines_inside_limits(ax) -> bool:
    lo_x, hi_x = sorted(ax.get_xlim())
    lo_y, hi_y = sorted(ax.get_ylim())
    for line in ax.get_lines():
        if line.get_label() == "landmarks":  # context, drawn where they are
            continue
        x, y = (np.asarray(v, float) for v in line.get_data())
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.any() and (
            x[ok].min() < lo_x or x[ok].max() > hi_x or y[ok].min() < lo_y or y[ok].max() > hi_y
        ):
            return False
    return True


def test_link_rates_are_shares_of_sensed_links():
    links = {
        "step": np.array([1, 1, 1, 1, 2, 2]),
        "i": np.array([0, 0, 0, 1, 0, 1]),
        "triggered": np.array([True, False, False, True, False, False]),
    }
    per_robot, team = link_rates(links, 3, 3)
    np.testing.assert_allclose(per_robot[0], [1 / 3, 1.0, np.nan])
    np.testing.assert_allclose(per_robot[1], [0.0, 0.0, np.nan])
    assert np.isnan(per_robot[2]).all()
    np.testing.assert_allclose(team[:2], [0.5, 0.0])


def test_transmission_raster_is_not_a_solid_line(run, tmp_path):
    est = run.estimators["ckf"]
    per_robot, team = link_rates(est.links, len(run.time), run.truth.shape[1])
    # The old figure marked a robot whenever ANY of its links transmitted: nearly solid.
    assert (est.raster > 0).mean() > 0.9
    # The share of links it shows is what the communication rate is made of.
    assert np.nanmean(per_robot) < 0.6
    assert np.nanmean(team) == pytest.approx(est.summary()["comm_rate"], rel=0.05)
    files = plots.plot_run(run, tmp_path)
    assert {p.name for p in files} == {"trajectories.png", "msle.png", "transmissions.png"}


def test_estimator_styles_differ_beyond_colour():
    looks = {
        (core.ESTIMATOR_STYLES[n]["ls"], core.ESTIMATOR_STYLES[n]["marker"])
        for n in ("ckf", "ukf", "ekf", "dr")
    }
    assert len(looks) == 4


def test_run_figures_fixed_layout_keeps_every_label_inside(run, tmp_path, captured):
    """The run figures have no layout engine (its measuring was a third of their cost):
    their fixed margins must still hold every tick label, axis label, title, legend and
    colour bar inside the canvas."""
    plots.plot_run(run, tmp_path)
    assert len(captured) == 3
    for fig in captured:
        assert fig.get_layout_engine() is None
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        canvas = fig.bbox
        for ax in fig.axes:
            box = ax.get_tightbbox(renderer)
            assert box.x0 >= canvas.x0 - 1 and box.y0 >= canvas.y0 - 1, (ax.get_label(), box)
            assert box.x1 <= canvas.x1 + 1 and box.y1 <= canvas.y1 + 1, (ax.get_label(), box)
    trajectories, msle, _ = captured
    assert lines_inside_limits(trajectories.axes[0])
    top, diff = msle.axes[:2]
    styles = {(ln.get_linestyle(), ln.get_marker()) for ln in top.get_lines()}
    assert len(styles) == 4  # ckf, ukf, ekf, dead reckoning
    assert {t.get_text() for t in diff.get_legend().get_texts()} == {"UKF", "EKF"}


def test_mrclam_small_multiples_hold_every_estimate(tmp_path, captured):
    result = run_mrclam(MRCLAM_FIXTURE, MRCLAMConfig(filters=("ckf", "ekf"), duration=30))
    plots.plot_mrclam_trajectories(result, tmp_path / "t.png")
    plots.plot_mrclam_errors(result, tmp_path / "e.png")
    traj, errors = captured
    panels = [ax for ax in traj.axes if ax.get_visible() and ax.axison]
    assert len(panels) == len(result.robots)
    for ax in panels:
        assert lines_inside_limits(ax)
        assert len(ax.get_lines()) == 1 + len(result.estimators) + 1  # truth, estimates, marks
    assert len(errors.axes) == 4
    diff = errors.axes[1]
    assert [t.get_text() for t in diff.get_legend().get_texts()] == ["EKF"]


def test_one_plotting_package():
    assert not hasattr(report_module, "_pyplot") and not hasattr(mrclam_module, "_pyplot")
    assert report_module.band_figure is plots.band_figure
    root = Path(plots.__file__).parent
    for src in [*root.glob("*.py"), Path(report_module.__file__), Path(mrclam_module.__file__)]:
        assert "tight_layout(" not in src.read_text(), src
