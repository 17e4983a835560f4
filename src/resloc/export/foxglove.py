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

from resloc.export.frames import frame_steps, msle_series, position_errors, step_rows
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
def _cylinder(x: float, y: float, yaw: float, size: tuple, color: dict, z: float = 0.0) -> dict:
    return {
        "pose": _pose(x, y, yaw, z),
        "size": {"x": size[0], "y": size[1], "z": size[2]},
        "bottom_scale": 1.0,
        "top_scale": 1.0,
        "color": color,
    }


def _update(entities: list[dict], deletions: list[dict] | None = None) -> dict:
    return {"deletions": deletions or [], "entities": entities}


def zones_update(rec, stamp: dict) -> dict:
    """``/scene/zones``: SDZs red, CDZs blue (ids ``sdz1``, ``cdz1``, ...)."""
    entities, seen = [], {"sdz": 0, "cdz": 0}
    for z in rec.zones:
        seen[z.kind] = seen.get(z.kind, 0) + 1
        rgb = (0.9, 0.1, 0.1) if z.kind == "sdz" else (0.1, 0.2, 0.9)
        disc = _cylinder(
            float(z.center[0]),
            float(z.center[1]),
            0.0,
            (2 * z.radius, 2 * z.radius, 0.005),
            _color(rgb, 0.18),
            -0.01,
        )
        entities.append(
            _entity(
                stamp,
                f"{z.kind}{seen[z.kind]}",
                cylinders=[disc],
                texts=[_text(z.center, z.kind.upper())],
            )
        )
    return _update(entities)


def truth_update(rec, k: int, stamp: dict, unit: float) -> dict:
    """``/scene/truth``: true poses; a robot without ground truth at step ``k`` (MRCLAM gaps)
    is deleted, not left stale."""
    entities, gone = [], []
    for r, robot in enumerate(rec.robots):
        if not rec.valid[k, r]:
            gone.append({"timestamp": stamp, "type": 0, "id": robot})
            continue
        entities.append(
            _entity(
                stamp,
                robot,
                arrows=[_arrow(rec.truth[k, r], (0.2, 0.2, 0.2), unit, 0.8)],
                texts=[_text(rec.truth[k, r, :2] + 1.5 * unit, robot)],
            )
        )
    return _update(entities, gone)


def estimate_update(rec, name: str, ellipses: np.ndarray, k: int, stamp: dict, unit: float):
    """``/scene/<est>``: estimated poses with their 95 % ellipses (``ellipses: (K, N, 3)``)."""
    rgb = ESTIMATOR_RGB.get(name, (0.6, 0.2, 0.7))
    track = rec.estimates[name][k]
    entities = []
    for r, robot in enumerate(rec.robots):
        a, b, angle = (float(v) for v in ellipses[k, r])
        x, y = float(track[r, 0]), float(track[r, 1])
        disc = _cylinder(x, y, angle, (2 * a, 2 * b, 0.002), _color(rgb, 0.25))
        entities.append(
            _entity(stamp, robot, arrows=[_arrow(track[r], rgb, unit)], cylinders=[disc])
        )
    return _update(entities)


def link_updates(rec, name: str, rows: np.ndarray, k: int, stamp: dict):
    """``/scene/<est>/links`` and ``/rejections`` for the link ``rows`` since the previous
    frame, drawn between the estimated positions at step ``k`` (landmarks where they are).

    Returns
    -------
    links, rejections : dict
    sent, rejected : int
    """
    flags = rec.outcomes[name]
    sent = rows[flags["triggered"][rows]]
    rejected = rows[flags["detected"][rows]]
    pos = np.vstack([rec.estimates[name][k, :, :2], rec.landmarks])
    i, j = rec.links["i"], rec.links["j"]

    def segments(sel: np.ndarray) -> list:
        return [pt for e in sel for pt in (pos[j[e]], pos[i[e]])]

    delivered = flags["delivered"][sent]
    lines = [
        _lines(segments(sel), rgb, 2.0)
        for sel, rgb in ((sent[delivered], (0.1, 0.7, 0.2)), (sent[~delivered], (1.0, 0.55, 0.0)))
        if len(sel)
    ]
    rej = [_lines(segments(rejected), (0.9, 0.0, 0.0), 3.0)] if len(rejected) else []
    return (
        _update([_entity(stamp, "links", lines=lines)]),
        _update([_entity(stamp, "rejections", lines=rej)]),
        len(sent),
        len(rejected),
    )


def transforms(rec, name: str, k: int, stamp: dict) -> dict:
    """``/tf``: ``map -> robotN/base_link`` at estimator ``name``'s poses."""
    return {
        "transforms": [
            {
                "timestamp": stamp,
                "parent_frame_id": "map",
                "child_frame_id": f"{robot}/base_link",
                "translation": {"x": float(p[0]), "y": float(p[1]), "z": 0.0},
                "rotation": _pose(0.0, 0.0, float(p[2]))["orientation"],
            }
            for robot, p in zip(rec.robots, rec.estimates[name][k], strict=True)
        ]
    }


class _JsonMcap:
    """An MCAP writer of JSON messages with the :data:`SCHEMAS`, counting per topic."""

    def __init__(self, fh):
        from mcap.writer import Writer

        self.mcap = Writer(fh)
        self.mcap.start(profile="", library="resloc")
        self.schemas = {
            name: self.mcap.register_schema(name, "jsonschema", json.dumps(s).encode())
            for name, s in SCHEMAS.items()
        }
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def put(self, topic: str, schema: str, msg: dict, ns: int) -> None:
        if topic not in self.channels:
            self.channels[topic] = self.mcap.register_channel(topic, "json", self.schemas[schema])
            self.counts[topic] = 0
        data = json.dumps(msg, separators=(",", ":")).encode()
        self.mcap.add_message(self.channels[topic], log_time=ns, data=data, publish_time=ns)
        self.counts[topic] += 1


def write(rec, target: Path, options) -> dict:
    """Write the scene ``target`` (one MCAP file). Returns message counts per topic."""
    steps = frame_steps(rec.time, options.rate if options.rate is not None else DEFAULT_RATE)
    chosen = options.estimator or (rec.filters[0] if rec.filters else next(iter(rec.estimates)))
    span = np.ptp(rec.truth[..., :2][rec.valid], axis=0).max() if rec.valid.any() else 1.0
    unit = max(float(span), 0.5) / 60.0  # arrow size: a sixtieth of the arena
    msle = {n: msle_series(rec, n) for n in rec.estimates}
    errors = {n: position_errors(rec, n) for n in rec.estimates}
    ellipses = {n: covariance_ellipse(c) for n, c in rec.covariances.items()}
    scene = "foxglove.SceneUpdate"
    with open(target, "wb") as fh:
        out = _JsonMcap(fh)
        prev = -1
        for k in steps:
            ns = round((rec.t0 + float(rec.time[k])) * 1e9)
            stamp = {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}
            out.put("/scene/zones", scene, zones_update(rec, stamp), ns)
            out.put("/scene/truth", scene, truth_update(rec, k, stamp, unit), ns)
            rows = step_rows(rec.links["step"], prev, k)
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
            for name in rec.estimates:
                est = estimate_update(rec, name, ellipses[name], k, stamp, unit)
                out.put(f"/scene/{name}", scene, est, ns)
                links, rejections, sent, rejected = link_updates(rec, name, rows, k, stamp)
                out.put(f"/scene/{name}/links", scene, links, ns)
                out.put(f"/scene/{name}/rejections", scene, rejections, ns)
                metrics["transmitted"][name] = sent
                metrics["rejected"][name] = rejected
            out.put("/tf", "foxglove.FrameTransforms", transforms(rec, chosen, k, stamp), ns)
            out.put("/metrics", "resloc.Metrics", metrics, ns)
            prev = k
        out.mcap.finish()
    return {"topics": out.counts, "steps": len(steps), "tf_estimator": chosen}


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
