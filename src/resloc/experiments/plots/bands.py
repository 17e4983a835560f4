"""Figures of studies over seeds (reproduction report, sweeps): means with 95 % bands or
error bars, and transmission rasters."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resloc.experiments.plots.core import COLORS, figure, save
from resloc.experiments.plots.run import plot_transmissions
from resloc.experiments.stats import Estimate, mean_ci_series

__all__ = ["Curve", "band_figure", "errorbar_figure", "raster_figure", "xy_errorbar_figure"]

_DPI = 100


@dataclass
class Curve:
    """A per-seed time series to draw as mean and 95% band.

    Attributes
    ----------
    label : str
    time : ndarray, shape (steps,)
    samples : ndarray, shape (steps, T)
        One column per seed (``nan`` rows are skipped).
    color, style : str, optional
        ``style`` is a matplotlib format (``"-"``, ``"--o"``).
    """

    label: str
    time: np.ndarray
    samples: np.ndarray
    color: str | None = None
    style: str = "-"


def _positive_floor(values: np.ndarray) -> float:
    pos = values[np.isfinite(values) & (values > 0)]
    return float(pos.min()) * 0.5 if pos.size else 1e-12


def _finish(plt, fig, ax, title: str, path) -> Path:
    """Title, grid, legend, save and close a report figure."""
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save(plt, fig, path, _DPI)


def band_figure(
    path: Path,
    curves: Sequence[Curve],
    title: str,
    ylabel: str = "MSLE (m$^2$)",
    logy: bool = True,
) -> Path:
    """Mean over seeds (line) and its 95% Student-t band (shaded) for each curve.

    On a log axis the lower edge of a band is clipped at half the smallest positive mean.
    """
    plt, fig, ax = figure(figsize=(7, 4))
    for k, c in enumerate(curves):
        ok = np.isfinite(c.samples).any(axis=1)
        mean, half = mean_ci_series(c.samples[ok])
        t = np.asarray(c.time)[ok]
        color = c.color or f"C{k}"
        ax.plot(t, mean, c.style, color=color, label=c.label, lw=1.3, markevery=0.1, ms=4)
        if np.isfinite(half).any():
            lo, hi = mean - half, mean + half
            if logy:
                lo = np.maximum(lo, _positive_floor(mean))
            ax.fill_between(t, lo, hi, color=color, alpha=0.2, lw=0)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    return _finish(plt, fig, ax, title, path)


def _yerr(est: Sequence[Estimate], logy: bool) -> tuple[np.ndarray, np.ndarray]:
    mean = np.array([e.mean for e in est], float)
    half = np.array([e.half if math.isfinite(e.half) else 0.0 for e in est], float)
    lower = np.minimum(half, mean * 0.999) if logy else half
    return mean, np.vstack([lower, half])


def errorbar_figure(
    path: Path,
    x: Sequence,
    series: dict[str, Sequence[Estimate]],
    xlabel: str,
    ylabel: str,
    title: str,
    logy: bool = False,
    hline: tuple[float, str] | None = None,
) -> Path:
    """Mean and 95% CI bars of each series against ``x`` (numbers, or categories)."""
    plt, fig, ax = figure(figsize=(6.5, 4))
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in x)
    xs = np.asarray(x, float) if numeric else np.arange(len(x), dtype=float)
    n = max(1, len(series))
    span = (xs.max() - xs.min()) if xs.size > 1 else 1.0
    markers = "osv^Dx"
    for k, (label, est) in enumerate(series.items()):
        mean, err = _yerr(est, logy)
        shift = (k - (n - 1) / 2) * span * 0.008
        ax.errorbar(
            xs + shift,
            mean,
            yerr=err,
            marker=markers[k % len(markers)],
            ms=4,
            capsize=3,
            lw=1.2,
            color=COLORS.get(label, f"C{k}"),
            label=label.upper() if label in COLORS else label,
        )
    if hline is not None:
        ax.axhline(hline[0], color="k", ls=":", lw=1, label=hline[1])
    if not numeric:
        ax.set_xticks(xs, [str(v) for v in x])
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    return _finish(plt, fig, ax, title, path)


def xy_errorbar_figure(
    path: Path,
    x: Sequence[Estimate],
    y: Sequence[Estimate],
    labels: Sequence[str],
    xlabel: str,
    ylabel: str,
    title: str,
    logy: bool = False,
) -> Path:
    """Points with 95% CI bars on both axes, each annotated (e.g. MSLE against the measured
    communication rate, one point per trigger setting)."""
    plt, fig, ax = figure(figsize=(6.5, 4))
    xm, xerr = _yerr(x, False)
    ym, yerr = _yerr(y, logy)
    order = np.argsort(xm)
    ax.plot(xm[order], ym[order], "-", color="tab:blue", lw=0.8, alpha=0.6)
    ax.errorbar(xm, ym, xerr=xerr, yerr=yerr, fmt="o", ms=4, capsize=3, color="tab:blue")
    for xi, yi, text in zip(xm, ym, labels, strict=True):
        ax.annotate(text, (xi, yi), textcoords="offset points", xytext=(4, 6), fontsize=8)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    return save(plt, fig, path, _DPI)


def raster_figure(
    path: Path,
    raster: np.ndarray,
    time: np.ndarray,
    title: str,
    links: dict | None = None,
) -> Path:
    """Transmission instances of one seed.

    With ``links`` (an ``EstimatorResult.links`` log) this is
    :func:`~resloc.experiments.plots.run.plot_transmissions`: per robot and step the share of
    its links it transmitted on, and the share of all links. Without, robot x time with the
    number of links on which the robot transmitted, averaged over short bins (about 200).

    Parameters
    ----------
    raster : ndarray, shape (steps, N)
        Transmissions attempted by each robot at each step.
    time : ndarray, shape (steps,)
    links : dict, optional
    """
    raster = np.asarray(raster, float)
    steps, n = raster.shape
    if links is not None:
        return plot_transmissions(time, links, n, path, title)
    width = max(1, steps // 200)
    nb = steps // width
    binned = raster[: nb * width].reshape(nb, width, n).mean(axis=1)
    t = np.asarray(time, float)
    t0 = t[0] - (t[1] - t[0] if t.size > 1 else 0.0)
    plt, fig, ax = figure(figsize=(7, 3.5))
    im = ax.imshow(
        binned.T,
        aspect="auto",
        origin="lower",
        interpolation="nearest",
        cmap="Blues",
        extent=(t0, t[nb * width - 1], 0.5, n + 0.5),
        vmin=0.0,
    )
    cb = fig.colorbar(im, ax=ax, pad=0.01)
    cb.set_label("links transmitted / step", fontsize=8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot")
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.set_title(title, fontsize=10)
    return save(plt, fig, path, _DPI)
