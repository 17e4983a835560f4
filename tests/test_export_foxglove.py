"""Foxglove scene: MCAP with JSON schemas, read back with the plain ``mcap`` reader; every
message field is declared in its schema; the layout file names the topics written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from export_helpers import make_mrclam_dir, make_run_dir
from resloc.experiments.recording import Recording
from resloc.export import ExportFormat, ExportOptions, export_run_dir
from resloc.export.geometry import covariance_ellipse

pytest.importorskip("mcap", reason="the export extra is installed by make test")
LAYOUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove_layout.json"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def scene(run_dir, tmp_path_factory):
    every_step = ExportOptions(rate=1000.0)
    out = tmp_path_factory.mktemp("exp")
    (res,) = export_run_dir(run_dir, [ExportFormat.FOXGLOVE], out, options=every_step)
    from mcap.reader import make_reader

    topics: dict[str, list] = {}
    schemas = {}
    with open(res.path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            schemas[schema.name] = json.loads(schema.data)
            topics.setdefault(channel.topic, []).append(
                (schema.name, message.log_time, json.loads(message.data))
            )
    return Recording.load(run_dir / "recording.npz"), topics, schemas


def undeclared(msg, schema, path="") -> list[str]:
    """Fields of ``msg`` its JSON schema does not declare (recursively)."""
    if isinstance(msg, dict):
        props = schema.get("properties")
        extra = schema.get("additionalProperties")
        out = []
        for key, value in msg.items():
            sub = props.get(key) if props else extra
            if sub is None:
                out.append(f"{path}.{key}")
            else:
                out += undeclared(value, sub, f"{path}.{key}")
        return out
    if isinstance(msg, list):
        return [p for item in msg for p in undeclared(item, schema["items"], path + "[]")]
    return []


def test_every_frame_has_the_whole_scene_with_foxglove_schemas(scene):
    rec, topics, schemas = scene
    K = len(rec.time)
    expected = {
        "/scene/zones": "foxglove.SceneUpdate",
        "/scene/truth": "foxglove.SceneUpdate",
        "/tf": "foxglove.FrameTransforms",
        "/metrics": "resloc.Metrics",
    }
    for name in ("ckf", "ekf", "dr"):
        for suffix in ("", "/links", "/rejections"):
            expected[f"/scene/{name}{suffix}"] = "foxglove.SceneUpdate"
    assert {t: msgs[0][0] for t, msgs in topics.items()} == expected
    assert all(len(msgs) == K for msgs in topics.values())
    for topic, msgs in topics.items():
        for schema_name, _, msg in msgs[:: max(1, K // 7)]:
            assert undeclared(msg, schemas[schema_name]) == [], topic
    zones = topics["/scene/zones"][-1][2]["entities"]
    assert sorted(e["id"] for e in zones) == ["cdz1", "sdz1"]
    assert zones[0]["cylinders"][0]["size"]["x"] == pytest.approx(2 * rec.zones[0].radius)


def test_estimates_ellipses_links_and_rejections_match_the_recording(scene):
    rec, topics, _ = scene
    k, r = 230, 3
    ent = topics["/scene/ekf"][k][2]["entities"][r]
    assert ent["id"] == rec.robots[r] and ent["frame_id"] == "map"
    pos = ent["arrows"][0]["pose"]["position"]
    assert [pos["x"], pos["y"]] == pytest.approx(rec.estimates["ekf"][k, r, :2].tolist())
    a, b, ang = covariance_ellipse(rec.covariances["ekf"][k, r])
    cyl = ent["cylinders"][0]
    assert [cyl["size"]["x"], cyl["size"]["y"]] == pytest.approx([2 * a, 2 * b])
    q = cyl["pose"]["orientation"]
    assert 2 * np.arctan2(q["z"], q["w"]) == pytest.approx(ang)
    # Links drawn this frame = links that transmitted at this step (2 points per link).
    flags, step = rec.outcomes["ckf"], rec.links["step"]
    at_k = step == k
    lines = topics["/scene/ckf/links"][k][2]["entities"][0]["lines"]
    assert sum(len(ln["points"]) for ln in lines) == 2 * int((flags["triggered"] & at_k).sum())
    total_rej = sum(
        len(ln["points"]) // 2
        for _, _, msg in topics["/scene/ckf/rejections"]
        for ln in msg["entities"][0]["lines"]
    )
    assert total_rej == flags["detected"].sum() > 0
    m = topics["/metrics"][k][2]
    assert m["transmitted"]["ckf"] == int((flags["triggered"] & at_k).sum())
    d = rec.estimates["ckf"][k, :, :2] - rec.truth[k, :, :2]
    assert m["position_error"]["ckf"][rec.robots[r]] == pytest.approx(np.hypot(*d[r]))
    assert m["msle"]["dr"] > m["msle"]["ckf"] > 0


def test_layout_file_shows_the_scene_topics(scene):
    _, topics, _ = scene
    layout = json.loads(LAYOUT.read_text())
    three_d = layout["configById"]["3D!resloc-scene"]
    assert three_d["followTf"] == "map"
    visible = {t for t, v in three_d["topics"].items() if v["visible"]}
    assert visible <= set(topics) and "/scene/ckf/links" in visible
    for panel in layout["configById"].values():
        for path in panel.get("paths", []):
            assert path["value"].split(".")[0] == "/metrics"
            key = path["value"].split(".")[1]
            assert key in topics["/metrics"][0][2]


def test_default_rate_is_ten_frames_per_second(run_dir, tmp_path):
    from mcap.reader import make_reader

    (res,) = export_run_dir(run_dir, [ExportFormat.FOXGLOVE], tmp_path)
    with open(res.path, "rb") as fh:
        stamps = [m.log_time for _, ch, m in make_reader(fh).iter_messages() if ch.topic == "/tf"]
    rec = Recording.load(run_dir / "recording.npz")
    dt = np.diff(stamps) * 1e-9
    assert stamps[-1] == round(rec.time[-1] * 1e9)  # the last step is always a frame
    assert np.median(dt) == pytest.approx(0.099, abs=0.001)  # 3 steps of 33 ms


def test_mrclam_scene_removes_robots_without_ground_truth(tmp_path):
    from mcap.reader import make_reader

    run = make_mrclam_dir(tmp_path / "m", duration=60.0)
    rec = Recording.load(run / "recording.npz")
    (res,) = export_run_dir(run, [ExportFormat.FOXGLOVE], options=ExportOptions(rate=1000.0))
    gone = []
    with open(res.path, "rb") as fh:
        for sc, _, message in make_reader(fh).iter_messages(topics=["/scene/truth"]):
            msg = json.loads(message.data)
            schema = json.loads(sc.data)
            assert undeclared(msg, schema) == []
            gone += [(message.log_time, d["id"]) for d in msg["deletions"]]
            shown = {e["id"] for e in msg["entities"]}
            assert shown.isdisjoint(d["id"] for d in msg["deletions"])
    k, r = np.nonzero(~rec.valid)
    expected = {
        (round((rec.t0 + rec.time[a]) * 1e9), rec.robots[b]) for a, b in zip(k, r, strict=True)
    }
    assert set(gone) == expected and len(expected) > 0
