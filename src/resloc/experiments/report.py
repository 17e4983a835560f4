"""Reports: a small document model rendered to Markdown and to self-contained HTML, and the
figures of the reproduction report (every curve a mean over seeds with its 95% band).

The HTML embeds every figure as a base64 PNG, so ``report.html`` can be mailed or archived
on its own; ``report.md`` links the same PNG files under ``figures/``.
"""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from resloc.experiments.stats import Estimate, mean_ci_series

__all__ = [
    "METRIC_LABELS",
    "Code",
    "Curve",
    "Heading",
    "Image",
    "Paragraph",
    "Report",
    "Table",
    "band_figure",
    "errorbar_figure",
    "raster_figure",
    "render_html",
    "render_markdown",
    "write_report",
    "xy_errorbar_figure",
]

METRIC_LABELS = {
    "msle_mean": "MSLE, time average (m$^2$)",
    "msle_final": "MSLE at the end (m$^2$)",
    "rmse_mean": "position RMSE, time average (m)",
    "rmse_final": "position RMSE at the end (m)",
    "nees_mean": "NEES, time average",
    "comm_rate": "average communication rate",
}
COLORS = {"ckf": "tab:blue", "ukf": "tab:orange", "ekf": "tab:green", "dr": "tab:gray"}
_DPI = 100


# --------------------------------------------------------------------------- document model
@dataclass
class Heading:
    """A section heading (``level`` 1-4)."""

    text: str
    level: int = 2


@dataclass
class Paragraph:
    """Text with inline ``**bold**`` and ```code``` only."""

    text: str


@dataclass
class Table:
    """A table of strings (inline markup as in :class:`Paragraph`)."""

    header: list[str]
    rows: list[list[str]]


@dataclass
class Image:
    """A PNG figure on disk, with its caption."""

    path: Path
    caption: str


@dataclass
class Code:
    """A verbatim block (``lang`` for Markdown highlighting)."""

    text: str
    lang: str = ""


Block = Heading | Paragraph | Table | Image | Code


@dataclass
class Report:
    """A titled list of blocks."""

    title: str
    blocks: list[Block] = field(default_factory=list)

    def add(self, *blocks: Block) -> None:
        """Append blocks."""
        self.blocks.extend(blocks)

    def headings(self) -> list[str]:
        """Every heading text, in order."""
        return [b.text for b in self.blocks if isinstance(b, Heading)]

    def images(self) -> list[Image]:
        """Every figure, in order."""
        return [b for b in self.blocks if isinstance(b, Image)]


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render_markdown(report: Report, root: Path) -> str:
    """Markdown text; figures are linked relative to ``root`` (the report's directory)."""
    lines = [f"# {report.title}", ""]
    for b in report.blocks:
        if isinstance(b, Heading):
            lines += ["#" * (b.level) + " " + b.text, ""]
        elif isinstance(b, Paragraph):
            lines += [b.text, ""]
        elif isinstance(b, Table):
            lines.append("| " + " | ".join(_md_cell(h) for h in b.header) + " |")
            lines.append("|" + "|".join("---" for _ in b.header) + "|")
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows]
            lines.append("")
        elif isinstance(b, Image):
            rel = Path(b.path).relative_to(root).as_posix()
            lines += [f"![{_md_cell(b.caption)}]({rel})", "", f"*{b.caption}*", ""]
        elif isinstance(b, Code):
            lines += [f"```{b.lang}", b.text.rstrip("\n"), "```", ""]
    return "\n".join(lines)


_INLINE = re.compile(r"\*\*(.+?)\*\*|`([^`]+)`")


def _html_inline(text: str) -> str:
    out, pos = [], 0
    for m in _INLINE.finditer(text):
        out.append(html.escape(text[pos : m.start()]))
        if m.group(1) is not None:
            out.append(f"<strong>{html.escape(m.group(1))}</strong>")
        else:
            out.append(f"<code>{html.escape(m.group(2))}</code>")
        pos = m.end()
    out.append(html.escape(text[pos:]))
    return "".join(out)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:980px;margin:2em auto;
padding:0 1em;line-height:1.45;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:0.92em}
th,td{border:1px solid #ccc;padding:4px 8px;text-align:left;vertical-align:top}
th{background:#f3f3f3} code{background:#f4f4f4;padding:0 3px}
pre{background:#f7f7f7;padding:0.8em;overflow-x:auto;font-size:0.85em}
figure{margin:1.2em 0} figure img{max-width:100%} figcaption{font-style:italic;font-size:0.9em}
td.holds{background:#e3f6e3} td.does-not-hold{background:#fbe3e3}
td.inconclusive{background:#fff6d8}
"""


def render_html(report: Report) -> str:
    """Self-contained HTML: every figure embedded as a base64 PNG."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(report.title)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(report.title)}</h1>",
    ]
    for b in report.blocks:
        if isinstance(b, Heading):
            parts.append(f'<h{b.level} id="{_slug(b.text)}">{_html_inline(b.text)}</h{b.level}>')
        elif isinstance(b, Paragraph):
            parts.append(f"<p>{_html_inline(b.text)}</p>")
        elif isinstance(b, Table):
            parts.append("<table><thead><tr>")
            parts += [f"<th>{_html_inline(h)}</th>" for h in b.header]
            parts.append("</tr></thead><tbody>")
            for row in b.rows:
                cells = []
                for c in row:
                    cls = _slug(c) if c in ("holds", "does not hold", "inconclusive") else ""
                    attr = f' class="{cls}"' if cls else ""
                    cells.append(f"<td{attr}>{_html_inline(c)}</td>")
                parts.append("<tr>" + "".join(cells) + "</tr>")
            parts.append("</tbody></table>")
        elif isinstance(b, Image):
            data = base64.b64encode(Path(b.path).read_bytes()).decode("ascii")
            parts.append(
                f'<figure><img alt="{html.escape(b.caption)}" '
                f'src="data:image/png;base64,{data}"><figcaption>{_html_inline(b.caption)}'
                "</figcaption></figure>"
            )
        elif isinstance(b, Code):
            parts.append(f"<pre><code>{html.escape(b.text)}</code></pre>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_report(report: Report, out: Path, stem: str = "report") -> tuple[Path, Path]:
    """Write ``out/<stem>.md`` and ``out/<stem>.html``; return both paths."""
    out = Path(out)
    md = out / f"{stem}.md"
    md.write_text(render_markdown(report, out), encoding="utf-8")
    page = out / f"{stem}.html"
    page.write_text(render_html(report), encoding="utf-8")
    return md, page


# --------------------------------------------------------------------------- figures
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
    """

    label: str
    time: np.ndarray
    samples: np.ndarray
    color: str | None = None
    style: str = "-"


def _pyplot():
    from resloc.experiments.plots import pyplot

    return pyplot()


def _positive_floor(values: np.ndarray) -> float:
    pos = values[np.isfinite(values) & (values > 0)]
    return float(pos.min()) * 0.5 if pos.size else 1e-12


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
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for k, c in enumerate(curves):
        ok = np.isfinite(c.samples).any(axis=1)
        mean, half = mean_ci_series(c.samples[ok])
        t = np.asarray(c.time)[ok]
        color = c.color or f"C{k}"
        ax.plot(t, mean, c.style, color=color, label=c.label, lw=1.3)
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
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in x)
    xs = np.asarray(x, float) if numeric else np.arange(len(x), dtype=float)
    n = max(1, len(series))
    span = (xs.max() - xs.min()) if xs.size > 1 else 1.0
    for k, (label, est) in enumerate(series.items()):
        mean, err = _yerr(est, logy)
        shift = (k - (n - 1) / 2) * span * 0.008
        ax.errorbar(
            xs + shift,
            mean,
            yerr=err,
            marker="o",
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
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
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
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return Path(path)


def raster_figure(path: Path, raster: np.ndarray, time: np.ndarray, title: str) -> Path:
    """Transmission instances of one seed: robot x time, colour = links on which the robot
    transmitted, averaged over short time bins (about 200 bins over the run).

    Parameters
    ----------
    raster : ndarray, shape (steps, N)
        Transmissions attempted by each robot at each step.
    time : ndarray, shape (steps,)
    """
    plt = _pyplot()
    raster = np.asarray(raster, float)
    steps, n = raster.shape
    width = max(1, steps // 200)
    nb = steps // width
    binned = raster[: nb * width].reshape(nb, width, n).mean(axis=1)
    t = np.asarray(time, float)
    t0 = t[0] - (t[1] - t[0] if t.size > 1 else 0.0)
    fig, ax = plt.subplots(figsize=(7, 3.5))
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
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return Path(path)


def _finish(plt, fig, ax, title: str, path) -> Path:
    """Title, grid, legend, save and close a report figure."""
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return Path(path)
