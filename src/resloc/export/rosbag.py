"""A ROS 2 bag (MCAP storage) written with ``rosbags``: no ROS installation needed.

Topics (``robotN`` as in the recording; ``<est>`` is ``ckf``, ``ukf``, ``ekf`` or ``dr``):

* ``/robotN/<est>/pose``: ``geometry_msgs/msg/PoseWithCovarianceStamped`` in frame ``map``;
  the 3x3 pose covariance of ``(x, y, theta)`` sits in the x, y and yaw slots (0, 1, 5) of
  the row-major 6x6; z, roll and pitch are exact (0) in the plane.
* ``/robotN/ground_truth/pose``: ``geometry_msgs/msg/PoseStamped`` (only where it exists).
* ``/tf``: REP-105 frames per robot, ``map -> robotN/odom -> robotN/base_link`` (odom to
  base_link is dead reckoning, map to odom the correction of the chosen estimator) and
  ``map -> robotN/ground_truth``.
* ``/resloc/<est>/link_events``: ``resloc_msgs/msg/LinkEvents``, every link since the
  previous message on which something happened (attacked, rejected by the detector, or
  triggered), with its delivery and fusion. Its definition is stored in the bag, so any
  reader can decode it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from resloc.export.frames import frame_steps

__all__ = ["LINK_EVENTS_MSG", "LINK_EVENTS_TYPE", "typestore", "write"]

LINK_EVENTS_TYPE = "resloc_msgs/msg/LinkEvents"
LINK_EVENTS_MSG = """\
# Sensed links of one estimator since the previous message (robot and landmark names).
std_msgs/Header header
string estimator
string[] observer
string[] target
bool[] attacked
bool[] detected
bool[] triggered
bool[] delivered
bool[] fused
"""
#: Slots of x, y, yaw in a row-major 6x6 ROS pose covariance.
_SLOTS = np.array([0, 1, 5])


def typestore():
    """The ROS 2 Humble type store with ``resloc_msgs/msg/LinkEvents`` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(LINK_EVENTS_MSG, LINK_EVENTS_TYPE))
    return store


def pose_covariance_6x6(P: np.ndarray) -> np.ndarray:
    """Row-major 6x6 ROS covariances of planar 3x3 ones, shape (..., 36)."""
    out = np.zeros((*P.shape[:-2], 6, 6))
    out[..., _SLOTS[:, None], _SLOTS[None, :]] = P
    return out.reshape(*P.shape[:-2], 36)


def _compose_inverse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a * b^-1`` of planar poses ``(x, y, theta)``, shape (..., 3)."""
    dth = a[..., 2] - b[..., 2]
    c, s = np.cos(dth), np.sin(dth)
    x = a[..., 0] - (c * b[..., 0] - s * b[..., 1])
    y = a[..., 1] - (s * b[..., 0] + c * b[..., 1])
    return np.stack([x, y, dth], axis=-1)


def write(rec, target: Path, options) -> dict:
    """Write the bag directory ``target`` (``metadata.yaml`` + one ``.mcap``).

    Returns
    -------
    dict
        ``topics`` (name to message count) and ``steps`` written.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Point, Quat = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    Pose, Vec3 = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Vector3"]
    PoseCov = T["geometry_msgs/msg/PoseWithCovariance"]
    PoseCovStamped = T["geometry_msgs/msg/PoseWithCovarianceStamped"]
    PoseStamped = T["geometry_msgs/msg/PoseStamped"]
    Transform, TransformStamped = (
        T["geometry_msgs/msg/Transform"],
        T["geometry_msgs/msg/TransformStamped"],
    )
    TFMessage, LinkEvents = T["tf2_msgs/msg/TFMessage"], T[LINK_EVENTS_TYPE]

    chosen = options.estimator or (rec.filters[0] if rec.filters else next(iter(rec.estimates)))
    steps = frame_steps(rec.time, options.rate)
    N = rec.n_robots
    names = np.array(
        list(rec.robots) + [f"landmark{m + 1}" for m in range(len(rec.landmarks))], dtype=object
    )
    odom = rec.estimates.get("dr")
    counts: dict[str, int] = {}

    def pose(p: np.ndarray):
        half = 0.5 * float(p[2])
        return Pose(
            position=Point(x=float(p[0]), y=float(p[1]), z=0.0),
            orientation=Quat(x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half))),
        )

    def tf(stamp, parent: str, child: str, p: np.ndarray):
        half = 0.5 * float(p[2])
        return TransformStamped(
            header=Header(stamp=stamp, frame_id=parent),
            child_frame_id=child,
            transform=Transform(
                translation=Vec3(x=float(p[0]), y=float(p[1]), z=0.0),
                rotation=Quat(x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half))),
            ),
        )

    with Writer(Path(target), version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        conns = {}

        def connection(topic: str, msgtype: str):
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=store)
                counts[topic] = 0
            return conns[topic]

        def put(topic: str, msgtype: str, msg, ns: int) -> None:
            bag.write(connection(topic, msgtype), ns, store.serialize_cdr(msg, msgtype))
            counts[topic] += 1

        cov36 = {n: pose_covariance_6x6(c) for n, c in rec.covariances.items()}
        prev = -1
        for k in steps:
            ns = round((rec.t0 + float(rec.time[k])) * 1e9)
            stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            transforms = []
            for r, robot in enumerate(rec.robots):
                for name, track in rec.estimates.items():
                    msg = PoseCovStamped(
                        header=Header(stamp=stamp, frame_id="map"),
                        pose=PoseCov(pose=pose(track[k, r]), covariance=cov36[name][k, r]),
                    )
                    put(f"/{robot}/{name}/pose", PoseCovStamped.__msgtype__, msg, ns)
                if rec.valid[k, r]:
                    msg = PoseStamped(
                        header=Header(stamp=stamp, frame_id="map"), pose=pose(rec.truth[k, r])
                    )
                    put(f"/{robot}/ground_truth/pose", PoseStamped.__msgtype__, msg, ns)
                    transforms.append(tf(stamp, "map", f"{robot}/ground_truth", rec.truth[k, r]))
                base = odom[k, r] if odom is not None else np.zeros(3)
                correction = _compose_inverse(rec.estimates[chosen][k, r], base)
                transforms.append(tf(stamp, "map", f"{robot}/odom", correction))
                transforms.append(tf(stamp, f"{robot}/odom", f"{robot}/base_link", base))
            put("/tf", TFMessage.__msgtype__, TFMessage(transforms=transforms), ns)
            window = (rec.links["step"] > prev) & (rec.links["step"] <= k)
            for name, flags in rec.outcomes.items():
                # Events only: a link that was not attacked, rejected or triggered is silent.
                event = rec.links["attacked"] | flags["detected"] | flags["triggered"]
                rows = np.flatnonzero(window & event)
                msg = LinkEvents(
                    header=Header(stamp=stamp, frame_id="map"),
                    estimator=name,
                    observer=names[rec.links["i"][rows]].tolist(),
                    target=names[np.minimum(rec.links["j"][rows], len(names) - 1)].tolist(),
                    attacked=rec.links["attacked"][rows].astype(bool),
                    detected=flags["detected"][rows],
                    triggered=flags["triggered"][rows],
                    delivered=flags["delivered"][rows],
                    fused=flags["fused"][rows],
                )
                put(f"/resloc/{name}/link_events", LINK_EVENTS_TYPE, msg, ns)
            prev = k
    return {"topics": counts, "steps": len(steps), "tf_estimator": chosen, "robots": N}
