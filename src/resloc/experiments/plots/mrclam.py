"""Figures of an MRCLAM replay (``resloc mrclam``)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from resloc.experiments.plots.core import (
    ROBOT_COLORS,
    estimator_label,
    estimator_style,
    figure,
    pyplot,
    save,
)

__all__ = ["plot_mrclam_errors", "plot_mrclam_trajectories"]


def _stride(result, period: float = 0.1) -> int:
    return max(round(period / result.config.dt), 1)


def plot_mrclam_trajectories(result, path: Path) -> Path:
    """Small multiples, one panel per robot: its true path (black) and every estimator's
    (own colour and line style), with landmarks and danger zones. Each panel's axes hold the
    truth and every estimate, so a diverging estimate stays in view."""
    plt = pyplot()
    names = list(result.estimators)
    n = len(result.robots)
    cols = min(n, 3)
    rows = int(np.ceil(n / cols))
    plt, fig, axes = figure(rows, cols, figsize=(4.2 * cols, 4.3 * rows + 0.5), squeeze=False)
    stride = _stride(result)
    truth = result.truth[::stride]
    valid = result.valid[::stride]
    for r, (ax, subject) in enumerate(zip(axes.ravel(), result.robots, strict=False)):
        t = np.where(valid[:, r, None], truth[:, r, :2], np.nan)
        seen = [t]
        ax.plot(t[:, 0], t[:, 1], "-", color="k", lw=1.4, alpha=0.75, label="truth")
        texts = []
        for k, name in enumerate(names):
            est = result.estimators[name].track[::stride, r, :2]
            style = estimator_style(name, len(est), k)
            ax.plot(est[:, 0], est[:, 1], lw=0.9, alpha=0.9, **style)
            seen.append(est)
            texts.append(
                f"{name.upper()} {result.estimators[name].per_robot['position_rmse'][r]:.2f}"
            )
        lo = np.nanmin(np.vstack(seen), axis=0)
        hi = np.nanmax(np.vstack(seen), axis=0)
        pad = 0.08 * max(float((hi - lo).max()), 0.5)
        for zone_kind, color in (("sdz", "red"), ("cdz", "blue")):
            for z in result.zones.get(zone_kind, []):
                ax.add_patch(plt.Circle(z.center, z.radius, color=color, alpha=0.15))
        ax.plot(*result.landmark_xy.T, "k^", ms=4, alpha=0.6, label="landmarks")
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(f"robot {subject}: RMSE (m) " + ", ".join(texts), fontsize=8)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    fig.suptitle(
        f"{result.info['dataset']}: {result.info['replayed_s']:.0f} s, one panel per robot",
        fontsize=11,
    )
    return save(plt, fig, path)


def plot_mrclam_errors(result, path: Path) -> Path:
    """Position error (RMS over robots) per estimator, each filter's difference to the first
    filter (the curves coincide on MRCLAM), the heading error, and the position error of
    every robot for the first filter."""
    from resloc.experiments.mrclam import DEAD_RECKONING

    stride = _stride(result)
    t = result.time[::stride]
    plt, fig, axes = figure(
        4, 1, figsize=(8, 11), sharex=True, gridspec_kw={"height_ratios": [3, 1.6, 2, 2]}
    )
    pos = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-nan rows give nan on purpose
        for k, (name, est) in enumerate(result.estimators.items()):
            style = estimator_style(name, len(t), k)
            pos[name] = np.sqrt(np.nanmean(est.pos_err[::stride] ** 2, axis=1))
            he = np.degrees(np.sqrt(np.nanmean(est.heading_err[::stride] ** 2, axis=1)))
            axes[0].plot(t, pos[name], lw=0.9, **style)
            axes[2].plot(t, he, lw=0.9, **style)
    filters = [n for n in result.estimators if n != DEAD_RECKONING]
    first = filters[0] if filters else DEAD_RECKONING
    for k, name in enumerate(filters[1:], start=1):
        axes[1].plot(t, pos[name] - pos[first], lw=0.9, **estimator_style(name, len(t), k))
    axes[1].axhline(0.0, color=estimator_style(first)["color"], lw=1.0)
    if len(filters) < 2:
        axes[1].text(
            0.5, 0.5, "one filter: nothing to compare", ha="center", transform=axes[1].transAxes
        )
    est = result.estimators[first]
    for r, subject in enumerate(result.robots):
        axes[3].plot(
            t,
            est.pos_err[::stride, r],
            color=ROBOT_COLORS[r % len(ROBOT_COLORS)],
            lw=0.8,
            label=f"robot {subject}",
        )
    axes[0].set_ylabel("position error, RMS\nover robots (m)")
    axes[1].set_ylabel(f"minus {first.upper()} (m)")
    axes[2].set_ylabel("heading error, RMS\nover robots (deg)")
    axes[3].set_ylabel(f"{estimator_label(first)} position\nerror (m)")
    axes[3].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="upper left")
    axes[0].set_yscale("log")
    axes[0].set_ylim(bottom=1e-3)
    axes[0].set_title(f"{result.info['dataset']}: errors against ground truth")
    return save(plt, fig, path)
