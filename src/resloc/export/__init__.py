"""Exports of a run for the robotics ecosystem: TUM trajectories (evo), a ROS 2 bag (MCAP),
a Foxglove scene (MCAP, JSON schemas) and a self-contained HTML viewer.

Every format is one module with a ``write(recording, target, options) -> dict`` function,
registered once in :data:`WRITERS` and imported only when used: ``rosbags`` and ``mcap``
(the ``export`` extra) are never imported by ``resloc --help`` or a run without exports.
"""

from __future__ import annotations

import enum
import importlib
import importlib.util
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from resloc.errors import ConfigError
from resloc.signals import temporary_directory

__all__ = [
    "ExportFormat",
    "ExportOptions",
    "ExportResult",
    "check_dependencies",
    "export_recording",
    "export_run_dir",
    "parse_formats",
    "target_path",
]


class ExportFormat(enum.StrEnum):
    """Output formats of ``resloc export``."""

    TUM = "tum"
    ROSBAG = "rosbag"
    FOXGLOVE = "foxglove"
    HTML = "html"


@dataclass(frozen=True)
class _Writer:
    module: str  # resloc.export.<module>.write
    target: str  # file or directory name inside the export directory
    requires: tuple[str, ...] = ()  # importable modules the writer needs
    needs_events: bool = False  # covariances and link events (recording.npz)


#: One line per format: where it is written, what it needs.
WRITERS: dict[ExportFormat, _Writer] = {
    ExportFormat.TUM: _Writer("resloc.export.tum", "tum"),
    ExportFormat.ROSBAG: _Writer("resloc.export.rosbag", "rosbag2", ("rosbags",), True),
    ExportFormat.FOXGLOVE: _Writer("resloc.export.foxglove", "foxglove.mcap", ("mcap",), True),
    ExportFormat.HTML: _Writer("resloc.export.html", "viewer.html", (), True),
}


@dataclass(frozen=True)
class ExportOptions:
    """Choices shared by the formats.

    Attributes
    ----------
    estimator : str or None
        Estimator drawn as "the" estimate (``/tf``, viewer default); None: the first filter.
    rate : float or None
        Highest output rate (Hz) of the bag, the Foxglove scene and the viewer; None: every
        step for the bag, 10 Hz for the scene, at most ``max_frames`` for the viewer. TUM
        files keep every step.
    max_frames : int
        Most frames in the HTML viewer (its data is inlined in the page).
    """

    estimator: str | None = None
    rate: float | None = None
    max_frames: int = 2000


@dataclass
class ExportResult:
    """What one format wrote: its ``path`` and format-specific ``info``."""

    format: ExportFormat
    path: Path
    info: dict = field(default_factory=dict)


def parse_formats(text: str | list[str] | None, option: str = "--format") -> list[ExportFormat]:
    """Formats from ``"tum,rosbag"`` (or a list of such strings); ``all`` means every one."""
    if not text:
        return []
    items = [text] if isinstance(text, str) else list(text)
    out: list[ExportFormat] = []
    for item in items:
        for name in (s.strip().lower() for s in item.split(",")):
            if not name:
                continue
            if name == "all":
                out.extend(ExportFormat)
                continue
            try:
                out.append(ExportFormat(name))
            except ValueError:
                choices = ", ".join(f.value for f in ExportFormat)
                raise ConfigError(
                    f"{option}: unknown format {name!r}; use {choices} or all (comma-separated)"
                ) from None
    return list(dict.fromkeys(out))


def check_dependencies(formats: list[ExportFormat]) -> None:
    """Fail early (before a run) if a format's optional dependency is missing."""
    for fmt in formats:
        for module in WRITERS[fmt].requires:
            if importlib.util.find_spec(module) is None:
                raise ConfigError(
                    f"--format {fmt.value} needs the {module!r} package: "
                    "pip install 'resloc[export]'"
                )


def target_path(out: Path, fmt: ExportFormat) -> Path:
    """Where ``fmt`` is written inside the export directory ``out``."""
    return Path(out) / WRITERS[fmt].target


def export_recording(
    recording,
    formats: list[ExportFormat],
    out: Path,
    overwrite: bool = False,
    options: ExportOptions | None = None,
) -> list[ExportResult]:
    """Write ``recording`` in every format into directory ``out``.

    Each format is written to a temporary sibling and renamed into place when complete, so
    an interrupted export never leaves a half-written file at its final path. An existing
    target is replaced only with ``overwrite``.
    """
    options = options or ExportOptions()
    if options.estimator is not None and options.estimator not in recording.estimates:
        raise ConfigError(
            f"--estimator {options.estimator!r}: not in this run; "
            f"use one of {', '.join(recording.estimates)}"
        )
    if options.rate is not None and not options.rate > 0:
        raise ConfigError(f"--rate must be a positive number of Hz, got {options.rate}")
    check_dependencies(formats)
    from resloc.export.source import require

    for fmt in formats:
        if WRITERS[fmt].needs_events:
            require(recording, fmt.value, covariances=True, links=True)
    out = Path(out)
    for fmt in formats:
        target = target_path(out, fmt)
        if target.exists() and not overwrite:
            raise ConfigError(f"{target}: exists; pass --overwrite or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for fmt in formats:
        target = target_path(out, fmt)
        writer = importlib.import_module(WRITERS[fmt].module)
        with temporary_directory(f".{target.name}.tmp-", out) as tmp_dir:
            tmp = tmp_dir / target.name
            info = writer.write(recording, tmp, options)
            if target.is_dir():
                shutil.rmtree(target)
            os.replace(tmp, target)
        results.append(ExportResult(fmt, target, info))
    return results


def export_run_dir(
    run_dir: Path,
    formats: list[ExportFormat],
    out: Path | None = None,
    overwrite: bool = False,
    options: ExportOptions | None = None,
) -> list[ExportResult]:
    """Export a run directory (default ``out``: ``RUN_DIR/export``)."""
    from resloc.export.source import load_run_dir

    recording = load_run_dir(run_dir)
    return export_recording(
        recording, formats, Path(run_dir) / "export" if out is None else out, overwrite, options
    )
