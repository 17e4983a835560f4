"""A self-contained interactive HTML viewer of a run: one file, no network needed.

The page (``assets/viewer.html``) inlines its script, style and the run's data (JSON);
``#step=N&est=ckf`` in the URL selects a frame and an estimator. It shows true and
estimated poses with 95 % ellipses, the danger zones, the links that transmitted in each
frame (and the detector's rejections), the MSLE of every estimator over time and the
position error of every robot at the current frame.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import numpy as np

from resloc.export.frames import frame_steps, msle_series, position_errors
from resloc.export.geometry import covariance_ellipse

__all__ = ["viewer_data", "write"]

_PLACEHOLDER = "/*__RESLOC_DATA__*/"


def _rounded(a: np.ndarray, digits: int) -> list:
    """Flat list with ``nan`` as ``None`` (strict JSON), rounded to ``digits``."""
    flat = np.round(np.asarray(a, float).ravel(), digits)
    return [None if not np.isfinite(v) else float(v) for v in flat]


def viewer_data(rec, options) -> dict:
    """The JSON the page embeds.

    Frames are the steps kept by :func:`~resloc.export.frames.frame_steps`; the links of a
    frame are those since the previous frame, as flat ``[i, j, code, ...]`` with ``code``
    bit 0 = delivered, bit 1 = rejected by the detector (only triggered or rejected links).
    """
    steps = frame_steps(rec.time, options.rate, options.max_frames)
    names = list(rec.estimates)
    default = options.estimator or (rec.filters[0] if rec.filters else names[0])
    filters = rec.filters or names
    # The view holds the truth, the filters' estimates (not a diverging dead reckoning),
    # the zones and the landmarks, with a margin.
    pts = [rec.truth[..., :2][rec.valid]]
    pts += [rec.estimates[n][steps, :, :2].reshape(-1, 2) for n in filters]
    pts += [np.asarray(z.center, float)[None] + s * z.radius for z in rec.zones for s in (-1, 1)]
    if len(rec.landmarks):
        pts.append(rec.landmarks)
    allp = np.vstack(pts)
    allp = allp[np.isfinite(allp).all(axis=1)]
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    margin = 0.05 * max(float((hi - lo).max()), 0.5)
    link_step = rec.links["step"]
    bounds_idx = np.searchsorted(link_step, np.concatenate([[-1], steps]), side="right")
    links = {}
    for name in names:
        flags = rec.outcomes[name]
        keep = flags["triggered"] | flags["detected"]
        code = flags["delivered"].astype(np.int64) | (flags["detected"].astype(np.int64) << 1)
        per_frame = []
        for f in range(len(steps)):
            rows = np.arange(bounds_idx[f], bounds_idx[f + 1])
            rows = rows[keep[rows]]
            per_frame.append(
                np.column_stack([rec.links["i"][rows], rec.links["j"][rows], code[rows]])
                .ravel()
                .tolist()
            )
        links[name] = per_frame
    err = {n: position_errors(rec, n)[steps] for n in names}
    return {
        "name": rec.name,
        "robots": list(rec.robots),
        "labels": [r.removeprefix("robot") for r in rec.robots],
        "estimators": names,
        "default_estimator": default,
        "time": _rounded(rec.time[steps], 4),
        "steps": steps.tolist(),
        "bounds": [lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin],
        "zones": [
            {"kind": z.kind, "center": list(map(float, z.center)), "radius": float(z.radius)}
            for z in rec.zones
        ],
        "landmarks": np.asarray(rec.landmarks, float).reshape(-1, 2).tolist(),
        "valid": rec.valid[steps].astype(int).ravel().tolist(),
        "truth": _rounded(rec.truth[steps], 4),
        "est": {n: _rounded(rec.estimates[n][steps], 4) for n in names},
        "ell": {n: _rounded(covariance_ellipse(rec.covariances[n][steps]), 4) for n in names},
        "links": links,
        "msle": {n: _rounded(msle_series(rec, n)[steps], 8) for n in names},
        "err": {n: _rounded(e, 4) for n, e in err.items()},
        "err_max": {
            n: float(np.nanmax(e)) if np.isfinite(e).any() else 1.0 for n, e in err.items()
        },
    }


def write(rec, target: Path, options) -> dict:
    """Write the viewer page ``target``. Returns the frame count and the page size."""
    template = resources.files("resloc.export").joinpath("assets/viewer.html").read_text("utf-8")
    data = viewer_data(rec, options)
    # "</" cannot appear inside a <script> element: escape it in the JSON.
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    page = template.replace(_PLACEHOLDER, payload)
    Path(target).write_text(page, encoding="utf-8")
    return {"frames": len(data["time"]), "bytes": len(page.encode("utf-8"))}
