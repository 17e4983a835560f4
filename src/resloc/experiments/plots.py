"""Figures (matplotlib is imported lazily, inside each function, with the Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["draw_zones", "plot_msle", "plot_raster", "plot_run", "plot_trajectories", "pyplot"]

COLORS = {"ckf": "tab:blue", "ukf": "tab:orange", "ekf": "tab:green", "dr": "tab:gray"}


def pyplot():
    """``matplotlib.pyplot`` with a non-interactive backend (raises a clear error if absent)."""
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - depends on the install
        from resloc.errors import ConfigError

        raise ConfigError(
            "plots need matplotlib: pip install 'resloc[plot]' (or pass --no-plots)"
        ) from exc
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


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


def plot_trajectories(result, path: Path, estimator: str | None = None) -> Path:
    """True paths of trial 0 over the danger zones (and one estimator's, dashed)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_zones(ax, result.scenario)
    truth = result.truth
    for r in range(truth.shape[1]):
        ax.plot(truth[:, r, 0], truth[:, r, 1], color="k", lw=1.6 if r == 0 else 0.8, alpha=0.8)
        ax.plot(*truth[0, r, :2], "o", color="tab:green", ms=3)
        ax.plot(*truth[-1, r, :2], "s", color="tab:red", ms=3)
    if estimator is None:
        estimator = next((n for n in result.estimators if n != "dr"), None)
    if estimator is not None:
        est = result.estimators[estimator].track
        for r in range(est.shape[1]):
            ax.plot(
                est[:, r, 0],
                est[:, r, 1],
                "--",
                color=COLORS.get(estimator, "C0"),
                lw=0.7,
                label=f"{estimator.upper()} estimate" if r == 0 else None,
            )
    ax.plot([], [], color="k", label="truth (leader bold)")
    ax.set_aspect("equal")
    ax.set_xlim(-1.6, 1.6)
    ax.set_ylim(-1.6, 1.6)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    # A user's name is text, not mathtext: "$" would start a formula (and may not parse).
    name = result.scenario.run.name.replace("$", r"\$")
    ax.set_title(f"{name}: trajectories (trial 0)")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_msle(result, path: Path) -> Path:
    """MSLE over time per estimator (mean over trials, band = min..max when T > 1)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    t = result.time
    for name, est in result.estimators.items():
        m = est.series["msle"]
        ok = ~np.isnan(m).all(axis=1)
        ax.plot(t[ok], np.nanmean(m[ok], axis=1), color=COLORS.get(name), label=name.upper())
        if m.shape[1] > 1:
            ax.fill_between(
                t[ok], np.nanmin(m[ok], 1), np.nanmax(m[ok], 1), color=COLORS.get(name), alpha=0.15
            )
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("MSLE (m$^2$)")
    ax.set_title("Mean square localization error")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_raster(raster: np.ndarray, time: np.ndarray, path: Path, title: str) -> Path:
    """Transmission instances: robot x time raster (a dot where a robot transmitted)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    k, r = np.nonzero(raster)
    ax.scatter(time[k], r + 1, s=0.6, marker="|", color="tab:blue")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot")
    ax.set_ylim(0.5, raster.shape[1] + 0.5)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_run(result, out: Path) -> list[Path]:
    """The standard figures of a run."""
    out = Path(out)
    files = [
        plot_trajectories(result, out / "trajectories.png"),
        plot_msle(result, out / "msle.png"),
    ]
    first = next((n for n in result.estimators if n != "dr"), None)
    if first is not None:
        est = result.estimators[first]
        rate = est.summary()["comm_rate"]
        files.append(
            plot_raster(
                est.raster,
                result.time,
                out / "transmissions.png",
                f"{first.upper()} transmission instances (average communication rate = {rate:.2f})",
            )
        )
    return files
