"""What every figure shares: the lazy ``pyplot``, one style per estimator, saving.

Study figures use matplotlib's constrained layout, which places the axes at draw time by
measuring every label. The figures of every ``resloc run`` use :func:`fixed_figure`
instead: margins fixed in inches, no layout engine (the constrained layout's measuring cost
about a third of their drawing time).
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "COLORS",
    "ESTIMATOR_STYLES",
    "ROBOT_COLORS",
    "estimator_label",
    "estimator_style",
    "figure",
    "fixed_figure",
    "pyplot",
    "save",
]

#: One look per estimator: colour, line style and marker differ, so curves that coincide
#: (CKF, UKF and EKF often do) stay distinguishable, also in grey scale.
ESTIMATOR_STYLES = {
    "ckf": {"color": "tab:blue", "ls": "-", "marker": "o"},
    "ukf": {"color": "tab:orange", "ls": "--", "marker": "s"},
    "ekf": {"color": "tab:green", "ls": ":", "marker": "^"},
    "dr": {"color": "tab:gray", "ls": "-.", "marker": "x"},
}
COLORS = {name: s["color"] for name, s in ESTIMATOR_STYLES.items()}
ROBOT_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
DPI = 110


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


def figure(*args, **kwargs):
    """``plt.subplots`` with constrained layout; returns ``(plt, fig, axes)``."""
    plt = pyplot()
    fig, axes = plt.subplots(*args, layout="constrained", **kwargs)
    return plt, fig, axes


def fixed_figure(*args, margins=(0.85, 0.2, 0.55, 0.35), hspace: float = 0.08, **kwargs):
    """``plt.subplots`` with margins fixed in inches; returns ``(plt, fig, axes)``.

    Parameters
    ----------
    *args, **kwargs
        Passed to ``plt.subplots`` (``figsize`` in inches).
    margins : tuple of float
        Left, right, bottom and top margins in inches: room for the tick labels, the axis
        labels and the title at the default font sizes.
    hspace : float
        Vertical gap between rows, as a fraction of the mean axes height.
    """
    plt = pyplot()
    fig, axes = plt.subplots(*args, **kwargs)
    width, height = fig.get_size_inches()
    left, right, bottom, top = margins
    fig.subplots_adjust(
        left=left / width,
        right=1.0 - right / width,
        bottom=bottom / height,
        top=1.0 - top / height,
        hspace=hspace,
    )
    return plt, fig, axes


def save(plt, fig, path, dpi: int = DPI) -> Path:
    """Save and close ``fig``."""
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


def estimator_label(name: str) -> str:
    """``CKF``, ``UKF``, ``EKF`` or ``dead reckoning``."""
    return "dead reckoning" if name == "dr" else name.upper()


def estimator_style(name: str, n_points: int = 0, k: int = 0) -> dict:
    """Keyword arguments of ``ax.plot`` for estimator ``name`` (``k``: fallback colour index;
    ``n_points``: markers every ~1/10 of the curve, offset per estimator so they don't stack)."""
    s = dict(ESTIMATOR_STYLES.get(name, {"color": f"C{k}", "ls": "-", "marker": "d"}))
    if n_points > 0 and s.get("marker"):
        every = max(1, n_points // 10)
        order = list(ESTIMATOR_STYLES).index(name) if name in ESTIMATOR_STYLES else k
        s["markevery"] = (min(order * every // 4, n_points - 1), every)
        s["ms"] = 4
    else:
        s.pop("marker", None)
    s["label"] = estimator_label(name)
    return s
