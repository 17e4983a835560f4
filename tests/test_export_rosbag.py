"""ROS 2 bag export: read back with the plain ``mcap`` reader (CDR decoded independently of
the bag writer), by evo's ROS 2 bag reader and by ``evo_ape bag2``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from export_helpers import make_mrclam_dir, make_run_dir
from resloc.experiments.recording import Recording
from resloc.export import ExportFormat, ExportOptions, export_run_dir

pytest.importorskip("rosbags", reason="the export extra is installed by make test")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def bag(run_dir, tmp_path_factory):
    (res,) = export_run_dir(run_dir, [ExportFormat.ROSBAG], tmp_path_factory.mktemp("exp"))
    return res


def read_mcap(path: Path) -> dict[str, list]:
    """``{topic: [(log_time, schema_name, schema_encoding, message_encoding, data)]}``."""
    from mcap.reader import make_reader

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            out.setdefault(channel.topic, []).append(
                (
                    message.log_time,
                    schema.name,
                    schema.encoding,
                    channel.message_encoding,
                    message.data,
                )
            )
    return out


def test_bag_is_mcap_with_every_topic_and_step(run_dir, bag):
    rec = Recording.load(run_dir / "recording.npz")
    (mcap_file,) = bag.path.glob("*.mcap")
    assert (bag.path / "metadata.yaml").is_file()
    topics = read_mcap(mcap_file)
    K = len(rec.time)
    for robot in ("robot1", "robot17"):
        for name in ("ckf", "ekf", "dr"):
            msgs = topics[f"/{robot}/{name}/pose"]
            assert len(msgs) == K
            assert {m[1:4] for m in msgs} == {
                ("geometry_msgs/msg/PoseWithCovarianceStamped", "ros2msg", "cdr")
            }
        assert topics[f"/{robot}/ground_truth/pose"][0][1] == "geometry_msgs/msg/PoseStamped"
    assert len(topics["/tf"]) == K and topics["/tf"][0][1] == "tf2_msgs/msg/TFMessage"
    assert topics["/resloc/ckf/link_events"][0][1] == "resloc_msgs/msg/LinkEvents"
    assert [m[0] for m in topics["/tf"]] == [round(t * 1e9) for t in rec.time]


def test_poses_covariances_tf_and_events_decode_to_the_recording(run_dir, bag):
    from resloc.export.rosbag import typestore

    store = typestore()
    rec = Recording.load(run_dir / "recording.npz")
    topics = read_mcap(next(bag.path.glob("*.mcap")))
    k, r = 200, 6
    msg = store.deserialize_cdr(topics["/robot7/ekf/pose"][k][4], topics["/robot7/ekf/pose"][k][1])
    assert msg.header.frame_id == "map"
    assert msg.pose.pose.position.x == pytest.approx(rec.estimates["ekf"][k, r, 0])
    q = msg.pose.pose.orientation
    assert 2 * np.arctan2(q.z, q.w) == pytest.approx(rec.estimates["ekf"][k, r, 2])
    C = msg.pose.covariance.reshape(6, 6)
    np.testing.assert_allclose(C[np.ix_([0, 1, 5], [0, 1, 5])], rec.covariances["ekf"][k, r])
    assert C[2, 2] == C[3, 3] == C[4, 4] == 0.0 and C[0, 0] > 0

    # /tf: map -> robot7/odom -> robot7/base_link composes to the CKF estimate (REP-105).
    tfm = store.deserialize_cdr(topics["/tf"][k][4], "tf2_msgs/msg/TFMessage")
    frames = {(t.header.frame_id, t.child_frame_id): t.transform for t in tfm.transforms}
    a, b = frames[("map", "robot7/odom")], frames[("robot7/odom", "robot7/base_link")]
    ya, yb = (2 * np.arctan2(t.rotation.z, t.rotation.w) for t in (a, b))
    x = a.translation.x + np.cos(ya) * b.translation.x - np.sin(ya) * b.translation.y
    y = a.translation.y + np.sin(ya) * b.translation.x + np.cos(ya) * b.translation.y
    np.testing.assert_allclose([x, y], rec.estimates["ckf"][k, r, :2], atol=1e-9)
    assert np.angle(np.exp(1j * (ya + yb - rec.estimates["ckf"][k, r, 2]))) == pytest.approx(0)
    np.testing.assert_allclose([b.translation.x, b.translation.y], rec.estimates["dr"][k, r, :2])
    assert ("map", "robot7/ground_truth") in frames

    # Link events: every detector rejection and every transmission of the run, once.
    totals = {"detected": 0, "triggered": 0, "attacked": 0}
    for _, schema, *_, data in topics["/resloc/ckf/link_events"]:
        ev = store.deserialize_cdr(data, schema)
        for key in totals:
            totals[key] += int(np.sum(getattr(ev, key)))
        assert len(ev.observer) == len(ev.target) == len(ev.fused)
    flags = rec.outcomes["ckf"]
    assert totals["detected"] == flags["detected"].sum() > 0
    assert totals["triggered"] == flags["triggered"].sum() > 0
    assert totals["attacked"] == rec.links["attacked"].sum() > 0


def test_evo_reads_the_bag_and_agrees_with_the_tum_alignment(run_dir, bag, tmp_path):
    from evo.core import metrics, sync
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    (tum,) = export_run_dir(run_dir, [ExportFormat.TUM], tmp_path)
    with Reader(bag.path) as reader:
        gt = file_interface.read_bag_trajectory(reader, "/robot4/ground_truth/pose")
        est = file_interface.read_bag_trajectory(reader, "/robot4/ckf/pose")
    ref, est = sync.associate_trajectories(gt, est)
    est.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(
        tum.info["ckf"]["robots"]["robot4"]["per_robot"], rel=1e-4
    )
    exe = Path(sys.executable).with_name("evo_ape")
    env = {**os.environ, "HOME": str(tmp_path), "MPLBACKEND": "Agg"}
    cli = subprocess.run(
        [str(exe), "bag2", str(bag.path), "/robot4/ground_truth/pose", "/robot4/ckf/pose", "-a"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert cli.returncode == 0, cli.stderr
    rmse = float(next(ln for ln in cli.stdout.splitlines() if "rmse" in ln).split()[-1])
    assert rmse == pytest.approx(tum.info["ckf"]["robots"]["robot4"]["per_robot"], rel=1e-3)


def test_mrclam_bag_has_absolute_stamps_landmark_targets_and_a_rate(tmp_path):
    run = make_mrclam_dir(tmp_path / "m")
    rec = Recording.load(run / "recording.npz")
    (res,) = export_run_dir(run, [ExportFormat.ROSBAG], options=ExportOptions(rate=10.0))
    topics = read_mcap(next(res.path.glob("*.mcap")))
    poses = topics["/robot1/ckf/pose"]
    assert len(poses) == pytest.approx(rec.time[-1] * 10 + 1, abs=1)  # 10 Hz, not 50 Hz
    assert poses[0][0] == round(rec.t0 * 1e9) and rec.t0 > 1e9  # Unix time of the dataset
    from resloc.export.rosbag import typestore

    store = typestore()
    targets = set()
    for _, schema, *_, data in topics["/resloc/ckf/link_events"]:
        targets |= set(store.deserialize_cdr(data, schema).target)
    assert any(t.startswith("landmark") for t in targets)
    assert any(t.startswith("robot") for t in targets)
