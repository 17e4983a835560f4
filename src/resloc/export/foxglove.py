"""A Foxglove scene: MCAP with JSON messages and JSON schemas, written with the plain ``mcap``
writer (no ``foxglove-sdk``: its field names changed between releases).

Open ``foxglove.mcap`` in Foxglove (or Lichtblick) with the layout ``docs/foxglove_layout.json``.
Topics (``<est>`` is each estimator; frame ``map``):

* ``/scene/zones`` (``foxglove.SceneUpdate``): SDZs (red) and CDZs (blue) as flat discs;
* ``/scene/truth``: true poses (grey arrows) and robot names;
* ``/scene/<est>``: estimated poses (arrows) and their 95 % position ellipses;
* ``/scene/<est>/links``: the links that transmitted since the previous frame (green lines
  from sender to observer; dashed orange where the jammer dropped it);
* ``/scene/<est>/rejections``: measurements the detector rejected (red lines, X at observer);
* ``/tf`` (``foxglove.FrameTransforms``): ``map -> robotN/base_link`` of the chosen estimator;
* ``/metrics`` (``resloc.Metrics``): MSLE per estimator and position error per robot, for
  the Plot panel (``/metrics.msle.ckf``).

Every frame republishes every entity (same ``id``), so seeking anywhere shows the full scene.
Frames are written at ``--rate`` Hz, by default :data:`DEFAULT_RATE` (10 Hz); links and
rejections accumulate over the steps between two frames.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from resloc.export.frames import frame_steps, msle_series, position_errors
from resloc.export.geometry import covariance_ellipse

__all__ = ["SCHEMAS", "write"]

#: Frames per second when ``--rate`` is not given (a scene, not data: keeps files small).
DEFAULT_RATE = 10.0
ESTIMATOR_RGB = {
    "ckf": (0.12, 0.47, 0.71),
    "ukf": (1.0, 0.5, 0.05),
    "ekf": (0.17, 0.63, 0.17),
    "dr": (0.5, 0.5, 0.5),
}


# ----------------------------------------------------------------------------- JSON schemas
def _obj(title: str | None, props: dict, required: list[str] | None = None) -> dict:
    out = {"type": "object", "properties": props}
    if title:
        out["title"] = title
    if required is not None:
        out["required"] = required
    return out


_NUM = {"type": "number"}
_TIME = _obj("time", {"sec": {"type": "integer"}, "nsec": {"type": "integer"}})
_VEC3 = _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM}, ["x", "y", "z"])
_POINT3 = _obj("foxglove.Point3", {"x": _NUM, "y": _NUM, "z": _NUM}, ["x", "y", "z"])
_QUAT = _obj("foxglove.Quaternion", {k: _NUM for k in "xyzw"}, list("xyzw"))
_COLOR = _obj("foxglove.Color", {k: _NUM for k in "rgba"}, list("rgba"))
_POSE = _obj("foxglove.Pose", {"position": _VEC3, "orientation": _QUAT})
_ARROW = _obj(
    "foxglove.ArrowPrimitive",
    {
        "pose": _POSE,
        "shaft_length": _NUM,
        "shaft_diameter": _NUM,
        "head_length": _NUM,
        "head_diameter": _NUM,
        "color": _COLOR,
    },
)
_CYLINDER = _obj(
    "foxglove.CylinderPrimitive",
    {"pose": _POSE, "size": _VEC3, "bottom_scale": _NUM, "top_scale": _NUM, "color": _COLOR},
)
_LINE = _obj(
    "foxglove.LinePrimitive",
    {
        "type": {"type": "integer", "description": "0 LINE_STRIP, 1 LINE_LOOP, 2 LINE_LIST"},
        "pose": _POSE,
        "thickness": _NUM,
        "scale_invariant": {"type": "boolean"},
        "points": {"type": "array", "items": _POINT3},
        "color": _COLOR,
        "colors": {"type": "array", "items": _COLOR},
        "indices": {"type": "array", "items": {"type": "integer"}},
    },
)
_TEXT = _obj(
    "foxglove.TextPrimitive",
    {
        "pose": _POSE,
        "billboard": {"type": "boolean"},
        "font_size": _NUM,
        "scale_invariant": {"type": "boolean"},
        "color": _COLOR,
        "text": {"type": "string"},
    },
)
_ENTITY = _obj(
    "foxglove.SceneEntity",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "id": {"type": "string"},
        "lifetime": _obj("duration", {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}),
        "frame_locked": {"type": "boolean"},
        "arrows": {"type": "array", "items": _ARROW},
        "cylinders": {"type": "array", "items": _CYLINDER},
        "lines": {"type": "array", "items": _LINE},
        "texts": {"type": "array", "items": _TEXT},
    },
)
_DELETION = _obj(
    "foxglove.SceneEntityDeletion",
    {
        "timestamp": _TIME,
        "type": {"type": "integer", "description": "0 MATCHING_ID, 1 ALL"},
        "id": {"type": "string"},
    },
)
_TRANSFORM = _obj(
    "foxglove.FrameTransform",
    {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VEC3,
        "rotation": _QUAT,
    },
)
#: Schema name -> JSON schema of the messages written.
SCHEMAS = {
    "foxglove.SceneUpdate": _obj(
        "foxglove.SceneUpdate",
        {
            "deletions": {"type": "array", "items": _DELETION},
            "entities": {"type": "array", "items": _ENTITY},
        },
    ),
    "foxglove.FrameTransforms": _obj(
        "foxglove.FrameTransforms", {"transforms": {"type": "array", "items": _TRANSFORM}}
    ),
    "resloc.Metrics": _obj(
        "resloc.Metrics",
        {
            "time_s": _NUM,
            "msle": {"type": "object", "additionalProperties": _NUM},
            "position_error": {
                "type": "object",
                "additionalProperties": {"type": "object", "additionalProperties": _NUM},
            },
            "transmitted": {"type": "object", "additionalProperties": {"type": "integer"}},
            "rejected": {"type": "object", "additionalProperties": {"type": "integer"}},
        },
    ),
}


# ----------------------------------------------------------------------------- primitives
def _pose(x: float, y: float, yaw: float = 0.0, z: float = 0.0) -> dict:
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {
            "x": 0.0,
            "y": 0.0,
            "z": float(np.sin(yaw / 2)),
            "w": float(np.cos(yaw / 2)),
        },
    }


def _color(rgb, a: float = 1.0) -> dict:
    return {"r": rgb[0], "g": rgb[1], "b": rgb[2], "a": a}


def _entity(stamp: dict, eid: str, **prims) -> dict:
    return {
        "timestamp": stamp,
        "frame_id": "map",
        "id": eid,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        **prims,
    }


def _arrow(p, rgb, unit: float, a: float = 1.0) -> dict:
    return {
        "pose": _pose(float(p[0]), float(p[1]), float(p[2]), 0.01),
        "shaft_length": 1.2 * unit,
        "shaft_diameter": 0.35 * unit,
        "head_length": 0.8 * unit,
        "head_diameter": 0.8 * unit,
        "color": _color(rgb, a),
    }


def _lines(points: list[tuple], rgb, thickness: float) -> dict:
    return {
        "type": 2,
        "pose": _pose(0.0, 0.0),
        "thickness": thickness,
        "scale_invariant": True,
        "points": [{"x": float(x), "y": float(y), "z": 0.02} for x, y in points],
        "color": _color(rgb, 0.9),
        "colors": [],
        "indices": [],
    }


# ----------------------------------------------------------------------------- writer
def write(rec, target: Path, options) -> dict:
    """Write the scene ``target`` (one MCAP file). Returns message counts per topic."""
    from mcap.writer import Writer

    steps = frame_steps(rec.time, options.rate if options.rate is not None else DEFAULT_RATE)
    chosen = options.estimator or (rec.filters[0] if rec.filters else next(iter(rec.estimates)))
    span = np.ptp(rec.truth[..., :2][rec.valid], axis=0).max() if rec.valid.any() else 1.0
    unit = max(float(span), 0.5) / 60.0  # arrow size: a sixtieth of the arena
    msle = {n: msle_series(rec, n) for n in rec.estimates}
    errors = {n: position_errors(rec, n) for n in rec.estimates}
    ellipses = {n: covariance_ellipse(c) for n, c in rec.covariances.items()}
    landmarks = rec.landmarks
    counts: dict[str, int] = {}
    with open(target, "wb") as fh:
        mcap = Writer(fh)
        mcap.start(profile="", library="resloc")
        schema_ids = {
            name: mcap.register_schema(name, "jsonschema", json.dumps(s).encode())
            for name, s in SCHEMAS.items()
        }
        channels: dict[str, int] = {}

        def put(topic: str, schema: str, msg: dict, ns: int) -> None:
            if topic not in channels:
                channels[topic] = mcap.register_channel(topic, "json", schema_ids[schema])
                counts[topic] = 0
            data = json.dumps(msg, separators=(",", ":")).encode()
            mcap.add_message(channels[topic], log_time=ns, data=data, publish_time=ns)
            counts[topic] += 1

        prev = -1
        for k in steps:
            ns = round((rec.t0 + float(rec.time[k])) * 1e9)
            stamp = {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}
            zones = [
                _entity(
                    stamp,
                    f"{z.kind}{sum(o.kind == z.kind for o in rec.zones[: n + 1])}",
                    cylinders=[
                        {
                            "pose": _pose(float(z.center[0]), float(z.center[1]), 0.0, -0.01),
                            "size": {"x": 2 * z.radius, "y": 2 * z.radius, "z": 0.005},
                            "bottom_scale": 1.0,
                            "top_scale": 1.0,
                            "color": _color(
                                (0.9, 0.1, 0.1) if z.kind == "sdz" else (0.1, 0.2, 0.9), 0.18
                            ),
                        }
                    ],
                    texts=[_text(z.center, z.kind.upper())],
                )
                for n, z in enumerate(rec.zones)
            ]
            put("/scene/zones", "foxglove.SceneUpdate", {"deletions": [], "entities": zones}, ns)
            truth = [
                _entity(
                    stamp,
                    robot,
                    arrows=[_arrow(rec.truth[k, r], (0.2, 0.2, 0.2), unit, 0.8)],
                    texts=[_text(rec.truth[k, r, :2] + 1.5 * unit, robot)],
                )
                for r, robot in enumerate(rec.robots)
                if rec.valid[k, r]
            ]
            # A robot without ground truth at this step (MRCLAM gaps) is removed, not left stale.
            gone = [
                {"timestamp": stamp, "type": 0, "id": robot}
                for r, robot in enumerate(rec.robots)
                if not rec.valid[k, r]
            ]
            put("/scene/truth", "foxglove.SceneUpdate", {"deletions": gone, "entities": truth}, ns)
            window = (rec.links["step"] > prev) & (rec.links["step"] <= k)
            metrics = {
                "time_s": float(rec.time[k]),
                "msle": {n: _finite(m[k]) for n, m in msle.items()},
                "position_error": {
                    n: {robot: _finite(e[k, r]) for r, robot in enumerate(rec.robots)}
                    for n, e in errors.items()
                },
                "transmitted": {},
                "rejected": {},
            }
            for name, track in rec.estimates.items():
                rgb = ESTIMATOR_RGB.get(name, (0.6, 0.2, 0.7))
                a, b, ang = ellipses[name][k].T
                est = [
                    _entity(
                        stamp,
                        robot,
                        arrows=[_arrow(track[k, r], rgb, unit)],
                        cylinders=[
                            {
                                "pose": _pose(
                                    float(track[k, r, 0]), float(track[k, r, 1]), float(ang[r])
                                ),
                                "size": {"x": 2 * float(a[r]), "y": 2 * float(b[r]), "z": 0.002},
                                "bottom_scale": 1.0,
                                "top_scale": 1.0,
                                "color": _color(rgb, 0.25),
                            }
                        ],
                    )
                    for r, robot in enumerate(rec.robots)
                ]
                put(
                    f"/scene/{name}", "foxglove.SceneUpdate", {"deletions": [], "entities": est}, ns
                )
                flags = rec.outcomes[name]
                sent = np.flatnonzero(window & flags["triggered"])
                rejected = np.flatnonzero(window & flags["detected"])
                pos = np.vstack([track[k, :, :2], landmarks])
                i, j = rec.links["i"], rec.links["j"]
                ok = flags["delivered"][sent]
                link_prims = []
                for mask, rgb_l in ((ok, (0.1, 0.7, 0.2)), (~ok, (1.0, 0.55, 0.0))):
                    pts = [pt for e in sent[mask] for pt in (pos[j[e]], pos[i[e]])]
                    if pts:
                        link_prims.append(_lines(pts, rgb_l, 2.0))
                links_msg = {
                    "deletions": [],
                    "entities": [_entity(stamp, "links", lines=link_prims)],
                }
                put(f"/scene/{name}/links", "foxglove.SceneUpdate", links_msg, ns)
                rej_pts = [pt for e in rejected for pt in (pos[j[e]], pos[i[e]])]
                rej = [_lines(rej_pts, (0.9, 0.0, 0.0), 3.0)] if rej_pts else []
                rej_msg = {"deletions": [], "entities": [_entity(stamp, "rejections", lines=rej)]}
                put(f"/scene/{name}/rejections", "foxglove.SceneUpdate", rej_msg, ns)
                metrics["transmitted"][name] = len(sent)
                metrics["rejected"][name] = len(rejected)
            tfs = [
                {
                    "timestamp": stamp,
                    "parent_frame_id": "map",
                    "child_frame_id": f"{robot}/base_link",
                    "translation": {"x": float(p[0]), "y": float(p[1]), "z": 0.0},
                    "rotation": _pose(0.0, 0.0, float(p[2]))["orientation"],
                }
                for robot, p in zip(rec.robots, rec.estimates[chosen][k], strict=True)
            ]
            put("/tf", "foxglove.FrameTransforms", {"transforms": tfs}, ns)
            put("/metrics", "resloc.Metrics", metrics, ns)
            prev = k
        mcap.finish()
    return {"topics": counts, "steps": len(steps), "tf_estimator": chosen}


def _text(xy, text: str) -> dict:
    return {
        "pose": _pose(float(xy[0]), float(xy[1]), 0.0, 0.03),
        "billboard": True,
        "font_size": 12.0,
        "scale_invariant": True,
        "color": _color((0.1, 0.1, 0.1), 0.9),
        "text": text,
    }


def _finite(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
