"""A ROS 2 subscriber nobody here wrote: `pyzeros` (an rmw_zenoh implementation in pure Python,
PyPI) subscribes to sensor_msgs/JointState on /joint_states and geometry_msgs/PoseStamped on
/lasertracker/pose (its own key expressions and RIHS01 type hashes, its own CDR decoder from
ros2_pyterfaces) and prints each message it decodes as one JSON line, with the wall time it
arrived. No keo code on the wire or in the decoding.

    python -m tests.pyzeros_listener ENDPOINT SECONDS
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from typing import Any


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


async def listen(endpoint: str, seconds: float) -> None:
    import pyzeros
    import zenoh
    from ros2_pyterfaces.cyclone.all_msgs import JointState, PoseStamped

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)

    def out(doc: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(doc) + "\n")
        sys.stdout.flush()

    async def joints(sub: Any) -> None:
        async for msg in sub.listen_reliable():
            out(
                {
                    "topic": "/joint_states",
                    "received": time.time(),
                    "stamp": _stamp(msg.header),
                    "name": list(msg.name),
                    "position": [float(v) for v in msg.position],
                    "velocity": [float(v) for v in msg.velocity],
                }
            )

    async def poses(sub: Any) -> None:
        async for msg in sub.listen_reliable():
            p, o = msg.pose.position, msg.pose.orientation
            out(
                {
                    "topic": "/lasertracker/pose",
                    "received": time.time(),
                    "stamp": _stamp(msg.header),
                    "frame_id": msg.header.frame_id,
                    "p": [p.x, p.y, p.z],
                    "q_xyzw": [o.x, o.y, o.z, o.w],
                }
            )

    with pyzeros.auto_context(node="pyzeros_listener", zenoh_session=session):
        joint_sub = pyzeros.Sub(JointState, "/joint_states")
        pose_sub = pyzeros.Sub(PoseStamped, "/lasertracker/pose")
        out({"ready": time.time()})
        tasks = [asyncio.ensure_future(joints(joint_sub)), asyncio.ensure_future(poses(pose_sub))]
        await asyncio.sleep(seconds)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        joint_sub.close()
        pose_sub.close()
    session.close()


if __name__ == "__main__":
    asyncio.run(listen(sys.argv[1], float(sys.argv[2])))
