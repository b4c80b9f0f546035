"""A ROS 2 driver simulator: publishes a scenario's joint states or tracker poses over
rmw_zenoh as a robot driver or a tracker driver would, so that keo's ROS 2 adapters cannot
tell it from one (docs/design.md §6).

- wire: the rmw_zenoh data key, CDR payload (rosbags), the 33-byte attachment and the node's
  and publisher's liveliness tokens, all from keo_service.live.ros2 (`Ros2Node`), on a Zenoh
  client session of the config's bus, as an rmw_zenoh node is a client of its router;
- messages: sensor_msgs/msg/JointState (the URDF's joint names, positions and velocities) on
  `robot.joint_states_topic`; geometry_msgs/msg/PoseStamped (metres, frame "tracker") on
  `tracker.pose_topic`, or PointStamped for a single reflector;
- stamps: ROS time is the host's wall clock (the "shared" clock domain): a row of scenario
  time t goes out at wall time start + t with header.stamp start + t, `start` the pass on
  the wall-clock grid of the scenario's period (`wall_clock_t0`, `_first_pass` of
  adapters/mock_devices.py), so a robot and a tracker mock started by hand agree;
- `loop_play`: the scenario again every `period_s`; `play_until`: the wall time after which
  nothing more is published.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import numpy as np

from keo_service.adapters.mock import MockSettings, TaskMock
from keo_service.adapters.mock_devices import JointTrack, PoseTrack, _first_pass
from keo_service.io.ros2_messages import (
    JOINT_STATE,
    POINT_STAMPED,
    POSE_STAMPED,
    joint_state,
    point_stamped,
    pose_stamped,
)
from keo_service.live.bus import session_for_client_async
from keo_service.live.ros2 import Ros2Node

log = logging.getLogger("keo.mock")

TRACKER_FRAME = "tracker"


class MockRos2Driver(TaskMock):
    """One ROS 2 driver node publishing one topic: `joints` (a JointTrack, with `names` in
    the track's column order) or `poses` (a PoseTrack, positions in metres)."""

    def __init__(
        self,
        config: Any,
        topic: str,
        settings: MockSettings,
        *,
        joints: JointTrack | None = None,
        names: list[str] | None = None,
        poses: PoseTrack | None = None,
        node_name: str = "mock_driver",
    ) -> None:
        if (joints is None) == (poses is None):
            raise ValueError("a ROS 2 mock plays joints or poses")
        t0 = settings.t0 if settings.t0 is not None else time.time() + 0.5
        self.config, self.topic, self.t0 = config, topic, t0
        self.joints, self.names, self.poses = joints, list(names or []), poses
        self.loop_play = settings.loop
        times = (joints if joints is not None else poses).t  # type: ignore[union-attr]
        self.times = np.asarray(times, dtype=float)
        self.period_s = settings.period_s or float(self.times[-1]) + 0.1
        self.play_until = settings.play_until
        self.node_name = node_name
        self.published = 0
        self._velocity: np.ndarray | None = None
        if joints is not None:
            q = np.asarray(joints.q, dtype=float)
            self._velocity = (
                np.gradient(q, self.times, axis=0) if self.times.size > 1 else np.zeros_like(q)
            )
        if poses is None:
            self.typename = JOINT_STATE
        else:
            self.typename = POSE_STAMPED if poses.quat is not None else POINT_STAMPED
        self._session: Any = None
        self._node: Ros2Node | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._session = await session_for_client_async(self.config)
        ros = self.config.ros2
        self._node = Ros2Node(self._session, self.node_name, ros.domain_id, ros.distro)
        publisher = self._node.publisher(self.topic, self.typename)
        log.info(
            "mock ROS 2 driver %s: %s on %s (domain %d, %s), playing from t0=%.3f",
            self.node_name,
            self.typename,
            publisher.key,
            ros.domain_id,
            ros.distro,
            self.t0,
        )
        self._task = asyncio.create_task(self._play(publisher), name="keo.mock.ros2")

    def summary(self) -> dict[str, object] | None:
        return None

    async def close(self) -> None:
        await self._stop_task()
        if self._node is not None:
            self._node.close()
        if self._session is not None:
            self._session.close()

    def message(self, i: int, stamp: float) -> Any:
        """Row `i` as its ROS message, stamped `stamp` (ROS time, s)."""
        assert self._node is not None
        types = self._node.store.types
        if self.joints is not None:
            assert self._velocity is not None
            return joint_state(types, stamp, self.names, self.joints.q[i], self._velocity[i])
        assert self.poses is not None
        if self.poses.quat is None:
            return point_stamped(types, stamp, TRACKER_FRAME, self.poses.p[i])
        return pose_stamped(types, stamp, TRACKER_FRAME, self.poses.p[i], self.poses.quat[i])

    async def _play(self, publisher: Any) -> None:
        start = self.t0
        if self.loop_play:
            start = _first_pass(self.t0, self.period_s, time.time())
        while True:
            i = int(np.searchsorted(self.times, time.time() - start))  # from now on
            while i < self.times.size:
                wall = start + float(self.times[i])
                if self.play_until is not None and wall > self.play_until:
                    return
                delay = wall - time.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                publisher.publish(self.message(i, wall))
                self.published += 1
                i += 1
            if not self.loop_play:
                return
            start += self.period_s


# ---- the protocol table's builders (io.protocols: MockSettings -> the mock) ----


def joint_state_mock(s: MockSettings, config: Any, run: Any) -> MockRos2Driver:
    """A ROS 2 robot driver: JointState on robot.joint_states_topic, the URDF's joint names."""
    from keo_service.io.cell import robot_from_config

    return MockRos2Driver(
        config,
        config.robot.joint_states_topic,
        s,
        joints=run.encoder,
        names=list(robot_from_config(config).joint_names),
        node_name="keo_mock_robot_driver",
    )


def pose_mock(s: MockSettings, config: Any, run: Any) -> MockRos2Driver:
    """A ROS 2 tracker driver: PoseStamped (PointStamped) on tracker.pose_topic, metres."""
    return MockRos2Driver(
        config, config.tracker.pose_topic, s, poses=run.tracker, node_name="keo_mock_tracker_driver"
    )
