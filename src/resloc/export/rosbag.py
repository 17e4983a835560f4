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

from resloc.export.frames import frame_steps, step_rows

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


class _Messages:
    """Builds the ROS 2 messages of one step (types from :func:`typestore`)."""

    def __init__(self, store):
        self.T = store.types

    def stamp(self, ns: int):
        return self.T["builtin_interfaces/msg/Time"](
            sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
        )

    def header(self, stamp, frame: str):
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def _quat(self, theta: float):
        half = 0.5 * float(theta)
        return self.T["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half))
        )

    def pose(self, p: np.ndarray):
        point = self.T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=0.0)
        return self.T["geometry_msgs/msg/Pose"](position=point, orientation=self._quat(p[2]))

    def pose_with_covariance(self, stamp, p: np.ndarray, cov36: np.ndarray):
        body = self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p), covariance=cov36)
        return self.T["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=self.header(stamp, "map"), pose=body
        )

    def pose_stamped(self, stamp, p: np.ndarray):
        return self.T["geometry_msgs/msg/PoseStamped"](
            header=self.header(stamp, "map"), pose=self.pose(p)
        )

    def transform(self, stamp, parent: str, child: str, p: np.ndarray):
        shift = self.T["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=0.0)
        return self.T["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp, parent),
            child_frame_id=child,
            transform=self.T["geometry_msgs/msg/Transform"](
                translation=shift, rotation=self._quat(p[2])
            ),
        )

    def tf(self, rec, k: int, stamp, chosen: str):
        """REP-105 frames of every robot at step ``k`` (see the module docstring)."""
        odom = rec.estimates.get("dr")
        out = []
        for r, robot in enumerate(rec.robots):
            if rec.valid[k, r]:
                out.append(self.transform(stamp, "map", f"{robot}/ground_truth", rec.truth[k, r]))
            base = odom[k, r] if odom is not None else np.zeros(3)
            correction = _compose_inverse(rec.estimates[chosen][k, r], base)
            out.append(self.transform(stamp, "map", f"{robot}/odom", correction))
            out.append(self.transform(stamp, f"{robot}/odom", f"{robot}/base_link", base))
        return self.T["tf2_msgs/msg/TFMessage"](transforms=out)

    def link_events(self, rec, name: str, rows: np.ndarray, stamp, names: np.ndarray):
        """The ``rows`` of ``rec.links`` on which something happened, for estimator ``name``."""
        flags, links = rec.outcomes[name], rec.links
        # Events only: a link that was not attacked, rejected or triggered is silent.
        rows = rows[links["attacked"][rows] | flags["detected"][rows] | flags["triggered"][rows]]
        return self.T[LINK_EVENTS_TYPE](
            header=self.header(stamp, "map"),
            estimator=name,
            observer=names[links["i"][rows]].tolist(),
            target=names[links["j"][rows]].tolist(),
            attacked=links["attacked"][rows].astype(bool),
            detected=flags["detected"][rows],
            triggered=flags["triggered"][rows],
            delivered=flags["delivered"][rows],
            fused=flags["fused"][rows],
        )


def write(rec, target: Path, options) -> dict:
    """Write the bag directory ``target`` (``metadata.yaml`` + one ``.mcap``).

    Returns
    -------
    dict
        ``topics`` (name to message count), ``steps`` written, the ``/tf`` estimator.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    make = _Messages(store)
    chosen = options.estimator or (rec.filters[0] if rec.filters else next(iter(rec.estimates)))
    steps = frame_steps(rec.time, options.rate)
    names = np.array(
        list(rec.robots) + [f"landmark{m + 1}" for m in range(len(rec.landmarks))], dtype=object
    )
    cov36 = {n: pose_covariance_6x6(c) for n, c in rec.covariances.items()}
    conns, counts = {}, {}
    with Writer(Path(target), version=9, storage_plugin=StoragePlugin.MCAP) as bag:

        def put(topic: str, msg, ns: int) -> None:
            msgtype = msg.__msgtype__
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=store)
                counts[topic] = 0
            bag.write(conns[topic], ns, store.serialize_cdr(msg, msgtype))
            counts[topic] += 1

        prev = -1
        for k in steps:
            ns = round((rec.t0 + float(rec.time[k])) * 1e9)
            stamp = make.stamp(ns)
            for r, robot in enumerate(rec.robots):
                for name, track in rec.estimates.items():
                    msg = make.pose_with_covariance(stamp, track[k, r], cov36[name][k, r])
                    put(f"/{robot}/{name}/pose", msg, ns)
                if rec.valid[k, r]:
                    put(
                        f"/{robot}/ground_truth/pose", make.pose_stamped(stamp, rec.truth[k, r]), ns
                    )
            put("/tf", make.tf(rec, k, stamp, chosen), ns)
            rows = step_rows(rec.links["step"], prev, k)
            for name in rec.outcomes:
                put(
                    f"/resloc/{name}/link_events",
                    make.link_events(rec, name, rows, stamp, names),
                    ns,
                )
            prev = k
    return {"topics": counts, "steps": len(steps), "tf_estimator": chosen}
