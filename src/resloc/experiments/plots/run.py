"""Figures of one simulated run (``resloc run``): trajectories, MSLE, transmissions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from resloc.experiments.plots.core import (
    estimator_label,
    estimator_style,
    fixed_figure,
    pyplot,
    save,
)

#: Title height in axes units, given explicitly: matplotlib otherwise measures the x-axis at
#: every save to lift the title over top tick labels, which these figures do not have.
TITLE_Y = 1.0

__all__ = [
    "draw_zones",
    "link_rates",
    "plot_msle",
    "plot_run",
    "plot_trajectories",
    "plot_transmissions",
]


def draw_zones(ax, scenario) -> None:
    """Draw SDZs (red) and CDZs (blue) as shaded discs on ``ax``."""
    plt = pyplot()
    for zones, color, label in (
        (scenario.world.sdz, "red", "SDZ"),
        (scenario.world.cdz, "blue", "CDZ"),
    ):
        for k, z in enumerate(zones):
            ax.add_patch(
                plt.Circle(
                    z.center, z.radius, color=color, alpha=0.18, label=label if k == 0 else None
                )
            )
            ax.add_patch(plt.Circle(z.center, z.radius, color=color, fill=False, lw=1.0))


def _limits(points: np.ndarray, margin: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """Square-ish bounds of ``points: (M, 2)`` with a relative margin."""
    p = points[np.isfinite(points).all(axis=1)]
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = margin * max(float((hi - lo).max()), 0.2)
    return lo - pad, hi + pad


def plot_trajectories(result, path: Path, estimator: str | None = None) -> Path:
    """True paths of trial 0 over the danger zones, and one estimator's (dashed); the axes
    hold the truth, the estimates and the zones (a diverging estimate stays in view)."""
    plt, fig, ax = fixed_figure(figsize=(6, 6), margins=(0.7, 0.15, 0.55, 0.35))
    draw_zones(ax, result.scenario)
    truth = result.truth
    for r in range(truth.shape[1]):
        ax.plot(truth[:, r, 0], truth[:, r, 1], color="k", lw=1.6 if r == 0 else 0.8, alpha=0.8)
        ax.plot(*truth[0, r, :2], "o", color="tab:green", ms=3)
        ax.plot(*truth[-1, r, :2], "s", color="tab:red", ms=3)
    if estimator is None:
        estimator = next((n for n in result.estimators if n != "dr"), None)
    seen = [truth[..., :2].reshape(-1, 2)]
    if estimator is not None:
        est = result.estimators[estimator].track
        style = estimator_style(estimator)
        for r in range(est.shape[1]):
            ax.plot(
                est[:, r, 0],
                est[:, r, 1],
                "--",
                color=style["color"],
                lw=0.7,
                label=f"{estimator_label(estimator)} estimate" if r == 0 else None,
            )
        seen.append(est[..., :2].reshape(-1, 2))
    zones = [*result.scenario.world.sdz, *result.scenario.world.cdz]
    seen += [np.asarray(z.center)[None] + s * z.radius for z in zones for s in (-1, 1)]
    lo, hi = _limits(np.vstack(seen))
    ax.plot([], [], color="k", label="truth (leader bold)")
    ax.set_aspect("equal")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    # A user's name is text, not mathtext: "$" would start a formula (and may not parse).
    name = result.scenario.run.name.replace("$", r"\$")
    ax.set_title(f"{name}: trajectories (trial 0)", y=TITLE_Y)
    ax.legend(loc="upper right", fontsize=8)
    return save(plt, fig, path)


def plot_msle(result, path: Path) -> Path:
    """MSLE over time per estimator (mean over trials, band = min..max when T > 1), and below
    it each filter's MSLE relative to the first filter's, so coinciding curves can be told
    apart."""
    plt, fig, (ax, diff) = fixed_figure(
        2, 1, figsize=(7, 5.2), sharex=True, gridspec_kw={"height_ratios": [3, 1.4]}
    )
    t = result.time
    means = {}
    for k, (name, est) in enumerate(result.estimators.items()):
        m = est.series["msle"]
        ok = ~np.isnan(m).all(axis=1)
        means[name] = np.where(ok, np.nanmean(np.where(ok[:, None], m, 0.0), axis=1), np.nan)
        style = estimator_style(name, int(ok.sum()), k)
        ax.plot(t[ok], means[name][ok], lw=1.2, **style)
        if m.shape[1] > 1:
            ax.fill_between(
                t[ok], np.nanmin(m[ok], 1), np.nanmax(m[ok], 1), color=style["color"], alpha=0.15
            )
    ax.set_yscale("log")
    ax.set_ylabel("MSLE (m$^2$)")
    ax.set_title("Mean square localization error", y=TITLE_Y)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    filters = [n for n in means if n != "dr"]
    if len(filters) > 1:
        ref = means[filters[0]]
        for k, name in enumerate(filters[1:], start=1):
            with np.errstate(invalid="ignore", divide="ignore"):
                rel = 100.0 * (means[name] - ref) / ref
            ok = np.isfinite(rel)
            diff.plot(t[ok], rel[ok], lw=1.0, **estimator_style(name, int(ok.sum()), k))
        diff.axhline(0.0, color=estimator_style(filters[0])["color"], lw=1.0)
        diff.set_ylabel(f"vs {filters[0].upper()} (%)")
        diff.legend(fontsize=7, loc="upper left")
    else:
        diff.text(0.5, 0.5, "one filter: nothing to compare", ha="center", transform=diff.transAxes)
    diff.grid(alpha=0.3)
    diff.set_xlabel("time (s)")
    return save(plt, fig, path)


def link_rates(links: dict, steps: int, n_robots: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-step transmission fractions from a link log.

    Parameters
    ----------
    links : dict of ndarray, each shape (M,)
        ``step`` (1-based), observer ``i`` and ``triggered`` of every sensed link.
    steps : int
    n_robots : int

    Returns
    -------
    per_robot : ndarray, shape (steps, N)
        Fraction of each robot's sensed links on which it transmitted (``nan``: none sensed).
    team : ndarray, shape (steps,)
        Fraction of all sensed links that transmitted.
    """
    k = np.asarray(links["step"]) - 1
    i = np.asarray(links["i"])
    sent = np.asarray(links["triggered"], float)
    cell = k * n_robots + i
    size = steps * n_robots
    sensed = np.bincount(cell, minlength=size).reshape(steps, n_robots)
    tx = np.bincount(cell, weights=sent, minlength=size).reshape(steps, n_robots)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_robot = np.where(sensed > 0, tx / sensed, np.nan)
        team = tx.sum(axis=1) / sensed.sum(axis=1)
    return per_robot, team


def plot_transmissions(
    time: np.ndarray, links: dict, n_robots: int, path: Path, title: str
) -> Path:
    """Transmission instances (the paper's Fig. 5e-h, truthfully): for every robot and step
    the fraction of its sensed links on which it transmitted (white: none, black: all), and
    below, the fraction of all links transmitting at each step.

    Parameters
    ----------
    time : ndarray, shape (steps,)
    links : dict
        A link log (``step``, ``i``, ``triggered``), e.g. ``EstimatorResult.links``.
    n_robots : int
    """
    per_robot, team = link_rates(links, len(time), n_robots)
    plt, fig, (ax, rate_ax) = fixed_figure(
        2,
        1,
        figsize=(7.5, 4.8),
        sharex=True,
        gridspec_kw={"height_ratios": [3, 1.2]},
        margins=(0.85, 1.05, 0.55, 0.35),
    )
    t = np.asarray(time, float)
    dt = t[1] - t[0] if t.size > 1 else 1.0
    cmap = pyplot().get_cmap("Greys").with_extremes(bad="#fbe9e9")  # no link sensed
    im = ax.imshow(
        per_robot.T,
        aspect="auto",
        origin="lower",
        interpolation="antialiased",
        cmap=cmap,
        vmin=0.0,
        vmax=1.0,
        extent=(t[0] - dt, t[-1], 0.5, n_robots + 0.5),
    )
    # The colour bar gets its own axes in the right margin, so both rows keep one x-axis.
    box = ax.get_position()
    cb = fig.colorbar(im, cax=fig.add_axes((box.x1 + 0.012, box.y0, 0.018, box.height)))
    cb.set_label("share of its links\ntransmitted", fontsize=8)
    ax.set_ylabel("robot")
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.set_title(title, fontsize=10, y=TITLE_Y)
    rate_ax.plot(t, team, color="k", lw=0.6)
    mean = float(np.nanmean(team)) if np.isfinite(team).any() else float("nan")
    rate_ax.axhline(mean, color="tab:red", lw=1.0, ls="--", label=f"mean {mean:.3f}")
    rate_ax.set_ylim(0, 1)
    rate_ax.set_ylabel("links\ntransmitting")
    rate_ax.set_xlabel("time (s)")
    rate_ax.legend(fontsize=7, loc="upper right")
    rate_ax.grid(alpha=0.3)
    return save(plt, fig, path)


def plot_run(result, out: Path) -> list[Path]:
    """The standard figures of a run."""
    out = Path(out)
    files = [
        plot_trajectories(result, out / "trajectories.png"),
        plot_msle(result, out / "msle.png"),
    ]
    first = next((n for n in result.estimators if n != "dr"), None)
    if first is not None and result.estimators[first].links is not None:
        est = result.estimators[first]
        rate = est.summary()["comm_rate"]
        files.append(
            plot_transmissions(
                result.time,
                est.links,
                result.truth.shape[1],
                out / "transmissions.png",
                f"{estimator_label(first)} transmission instances, trial 0 "
                f"(average communication rate = {rate:.2f})",
            )
        )
    return files
