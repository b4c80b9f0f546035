"""An independent ROS 2 peer for the tests: rmw_zenoh's wire format written here from its
design document with `rosbags` (CDR, type hashes) and `zenoh`, sharing no code with
keo_service.live.ros2. It plays joint states and tracker poses as a ROS 2 driver would, and
reads keo's estimate from the raw key expression."""

from __future__ import annotations

import os
import struct
import threading
import time
from typing import Any

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)


def dds(typename: str) -> str:
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def key(topic: str, typename: str, domain: int = 0) -> str:
    return f"{domain}/{topic.lstrip('/')}/{dds(typename)}/{STORE.hash_rihs01(typename)}"


def stamp(t: float) -> Any:
    sec = int(t)
    return STORE.types["builtin_interfaces/msg/Time"](sec, int((t - sec) * 1e9))


def header(t: float, frame: str) -> Any:
    return STORE.types["std_msgs/msg/Header"](stamp=stamp(t), frame_id=frame)


class Peer:
    """A ROS 2 node "sim_driver" publishing /joint_states and a tracker pose topic."""

    def __init__(self, endpoint: str) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        zid = str(self.session.zid())
        self.tokens = [self.session.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/sim")]
        self.publishers: dict[str, tuple[Any, bytes, list[int]]] = {}
        for entity, (topic, typename) in enumerate(
            [
                ("/joint_states", "sensor_msgs/msg/JointState"),
                ("/lasertracker/pose", "geometry_msgs/msg/PoseStamped"),
            ],
            start=1,
        ):
            k = key(topic, typename)
            pub = self.session.declare_publisher(k)
            self.publishers[typename] = (pub, os.urandom(16), [0])
            mangled = topic.replace("/", "%")
            self.tokens.append(
                self.session.liveliness().declare_token(
                    f"@ros2_lv/0/{zid}/0/{entity}/MP/%/%/sim/{mangled}/{dds(typename)}/"
                    f"{STORE.hash_rihs01(typename)}/::,10:,:,:,,"
                )
            )

    def publish(self, message: Any, typename: str) -> None:
        pub, gid, seq = self.publishers[typename]
        seq[0] += 1
        raw = STORE.serialize_cdr(message, typename)
        pub.put(bytes(raw), attachment=struct.pack("<qqB", seq[0], time.time_ns(), 16) + gid)

    def play(self, run: Any, joint_names: list[str], t0: float) -> threading.Thread:
        """Joint states and poses at their scenario times from wall time t0 (a thread)."""
        events = sorted(
            [(float(t), 0, i) for i, t in enumerate(run.encoder.t)]
            + [(float(t), 1, i) for i, t in enumerate(run.tracker.t)]
        )
        types = STORE.types

        def loop() -> None:
            for t, kind, i in events:
                delay = t0 + t - time.time()
                if delay > 0:
                    time.sleep(delay)
                if kind == 0:
                    q = run.encoder.q[i]
                    self.publish(
                        types["sensor_msgs/msg/JointState"](
                            header=header(t0 + t, ""),
                            name=["extra_joint", *reversed(joint_names)],
                            position=np.array([9.9, *q[::-1]]),
                            velocity=np.array([], dtype=float),
                            effort=np.array([], dtype=float),
                        ),
                        "sensor_msgs/msg/JointState",
                    )
                else:
                    p, (w, x, y, z) = run.tracker.p[i], run.tracker.quat[i]
                    pose = types["geometry_msgs/msg/Pose"](
                        position=types["geometry_msgs/msg/Point"](*map(float, p)),
                        orientation=types["geometry_msgs/msg/Quaternion"](
                            float(x), float(y), float(z), float(w)
                        ),
                    )
                    self.publish(
                        types["geometry_msgs/msg/PoseStamped"](
                            header=header(t0 + t, "tracker"), pose=pose
                        ),
                        "geometry_msgs/msg/PoseStamped",
                    )

        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        for token in self.tokens:
            token.undeclare()
        self.session.close()
