"""The figure of ``resloc compare``: the closed-loop detector ROC."""

from __future__ import annotations

from pathlib import Path

from resloc.experiments.plots.core import figure, save

__all__ = ["plot_roc"]


def plot_roc(rows: list[dict], path: Path) -> Path:
    """One panel per attack: each gate's true-positive against false-alarm rate.

    ``rows`` are :attr:`~resloc.experiments.compare.CompareResult.roc` rows (``attack``,
    ``gate``, ``tpr``, ``fpr``), each gate's listed strictest threshold first. In closed loop
    the points need not be monotone: each curve joins them from the loosest threshold (the
    fewest alarms) to the strictest.
    """
    attacks = list(dict.fromkeys(r["attack"] for r in rows))
    plt, fig, axes = figure(
        1, len(attacks), figsize=(4.5 * len(attacks), 4), sharey=True, squeeze=False
    )
    for ax, attack in zip(axes[0], attacks, strict=True):
        gates = dict.fromkeys(r["gate"] for r in rows)
        for gate, style in zip(gates, ("o-", "s-", "^-", "d-"), strict=False):
            curve = [r for r in rows if r["attack"] == attack and r["gate"] == gate][::-1]
            ax.plot(
                [r["fpr"]["mean"] for r in curve],
                [r["tpr"]["mean"] for r in curve],
                style,
                label=gate,
            )
        ax.set_xscale("symlog", linthresh=1e-3)
        ax.set_xlabel("false-alarm rate")
        ax.set_title(attack.replace("_", " "))
        ax.grid(True, alpha=0.3)
    axes[0, 0].set_ylabel("true-positive rate")
    axes[0, 0].legend()
    return save(plt, fig, path, dpi=120)
