"""ROS 2 MCAP recordings (rosbag2 with MCAP storage, written and read with rosbags).

`keo record --format mcap --out DIR` writes DIR/keo/ (metadata.yaml and keo.mcap): the joint
states as sensor_msgs/msg/JointState (the URDF's joint names), the tracker as
geometry_msgs/msg/PoseStamped (PointStamped for a single reflector) and keo's estimates as
geometry_msgs/msg/PoseWithCovarianceStamped, each with its message definition, so `ros2 bag`,
Foxglove and the `mcap` library read it. Stamps are the samples' stream times `t` (host clock)
in nanoseconds. `keo replay` and `keo estimate` read the joint and tracker topics back.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from keo_service.core.errors import DataFormatError
from keo_service.io import ros2_messages as rm
from keo_service.io.interchange import EncoderData, TrackerData

BAG_NAME = "keo"


def bag_dir(path: str | Path) -> Path:
    """The rosbag2 folder of a path: the folder itself, the folder of a .mcap file in it, or
    its `keo` subfolder (what `keo record --format mcap` writes)."""
    path = Path(path)
    for candidate in (path, path.parent, path / BAG_NAME):
        if (candidate / "metadata.yaml").is_file():
            return candidate
    raise DataFormatError(str(path), 0, "-", "not a ROS 2 MCAP recording (no metadata.yaml)")


def is_mcap(path: str | Path) -> bool:
    path = Path(path)
    if path.suffix == ".mcap":
        return True
    return path.is_dir() and any((c / "metadata.yaml").is_file() for c in (path, path / BAG_NAME))


class McapWriter:
    """Writes samples as they come; `close()` finishes the file (bounded memory)."""

    def __init__(
        self,
        out_dir: Path,
        joint_names: Sequence[str],
        cell: str,
        joint_topic: str = "/joint_states",
        pose_topic: str = "/lasertracker/pose",
        distro: str = "jazzy",
    ) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        self.path = out_dir / BAG_NAME
        self.store = rm.typestore(distro)
        self.types = self.store.types
        self.joint_names = list(joint_names)
        self.cell = cell
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._topics = {"joints": joint_topic, "pose": pose_topic}
        self._connections: dict[str, Any] = {}

    def _write(self, topic: str, typename: str, t: float, message: Any) -> None:
        conn = self._connections.get(topic + typename)
        if conn is None:
            conn = self._writer.add_connection(topic, typename, typestore=self.store)
            self._connections[topic + typename] = conn
        sec, nanosec = rm.stamp_of(t)
        raw = self.store.serialize_cdr(message, typename)
        self._writer.write(conn, sec * 1_000_000_000 + nanosec, raw)

    def joints(self, t: float, q: Sequence[float], dq: Sequence[float] | None) -> None:
        msg = rm.joint_state(self.types, t, self.joint_names, q, dq)
        self._write(self._topics["joints"], rm.JOINT_STATE, t, msg)

    def pose(self, t: float, p: Sequence[float], q_wxyz: Sequence[float] | None) -> None:
        if q_wxyz is None:
            msg = rm.point_stamped(self.types, t, "tracker", p)
            self._write(self._topics["pose"], rm.POINT_STAMPED, t, msg)
        else:
            msg = rm.pose_stamped(self.types, t, "tracker", p, q_wxyz)
            self._write(self._topics["pose"], rm.POSE_STAMPED, t, msg)

    def estimate(self, t: float, estimate: Sequence[float]) -> None:
        msg = rm.pose_with_covariance(self.types, t, rm.tool_frame(self.cell), estimate, None)
        self._write(rm.estimate_topic(self.cell), rm.POSE_COV, t, msg)

    def close(self) -> None:
        self._writer.close()


def read_mcap(path: str | Path, joint_names: Sequence[str]) -> tuple[EncoderData, TrackerData]:
    """The joint and tracker streams of a recording, joints picked by name into
    `joint_names`' order; times from the messages' header stamps."""
    folder = bag_dir(path)
    store = rm.typestore("jazzy")
    enc_t: list[float] = []
    enc_q: list[list[float]] = []
    trk_t: list[float] = []
    trk_p: list[list[float]] = []
    trk_q: list[list[float]] = []
    with Reader(folder) as reader:
        for conn, _timestamp, raw in reader.messages():
            if conn.msgtype == rm.JOINT_STATE:
                msg = store.deserialize_cdr(raw, conn.msgtype)
                index = {n: i for i, n in enumerate(msg.name)}
                missing = [n for n in joint_names if n not in index]
                if missing:
                    raise DataFormatError(
                        str(folder), 0, conn.topic, f"JointState without {', '.join(missing)}"
                    )
                enc_t.append(rm.seconds_of(msg.header))
                enc_q.append([float(msg.position[index[n]]) for n in joint_names])
            elif conn.msgtype in (rm.POSE_STAMPED, rm.POINT_STAMPED):
                msg = store.deserialize_cdr(raw, conn.msgtype)
                trk_t.append(rm.seconds_of(msg.header))
                if conn.msgtype == rm.POSE_STAMPED:
                    pos, o = msg.pose.position, msg.pose.orientation
                    trk_p.append([pos.x, pos.y, pos.z])
                    trk_q.append([o.w, o.x, o.y, o.z])
                else:
                    trk_p.append([msg.point.x, msg.point.y, msg.point.z])
    if not enc_t or not trk_t:
        raise DataFormatError(str(folder), 0, "-", "no joint states or no tracker poses in it")
    if trk_q and len(trk_q) != len(trk_t):
        raise DataFormatError(str(folder), 0, "-", "mixes 6-DoF poses and single points")
    encoder = EncoderData(t=np.asarray(enc_t), q=np.asarray(enc_q).reshape(len(enc_t), -1))
    tracker = TrackerData(
        t=np.asarray(trk_t),
        p=np.asarray(trk_p),
        quat=np.asarray(trk_q) if trk_q else None,
    )
    return encoder, tracker
