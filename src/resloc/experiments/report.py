"""Reports: a small document model rendered to Markdown and to self-contained HTML. The
figures of the reproduction report (every curve a mean over seeds with its 95% band) live
in :mod:`resloc.experiments.plots` and are re-exported here for the report builders.

The HTML embeds every figure as a base64 PNG, so ``report.html`` can be mailed or archived
on its own; ``report.md`` links the same PNG files under ``figures/``.
"""

from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass, field
from pathlib import Path

from resloc.experiments.plots.bands import (
    Curve,
    band_figure,
    errorbar_figure,
    raster_figure,
    xy_errorbar_figure,
)
from resloc.experiments.plots.core import COLORS

__all__ = [
    "COLORS",
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
