"""ROS 2 over rmw_zenoh, on keo's own Zenoh sessions: no bridge, no ROS installation.

What rmw_zenoh puts on the wire (ros2/rmw_zenoh, docs/design.md) and keo writes and reads:

- data key expression `<domain>/<topic without its leading slash>/<DDS type>/<type hash>`,
  e.g. `0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e...` (the hash is
  RIHS01 from Iron on; Humble writes `TypeHashNotSupported`);
- payload: CDR with its 4-byte encapsulation header (rosbags serialises it);
- attachment, 33 bytes: int64 LE sequence number, int64 LE source time [ns since epoch],
  one byte 16, the 16-byte publisher gid (rmw_zenoh subscribers drop samples without it);
  rmw_zenoh's gid is XXH3-128 of the publisher's liveliness token key expression, the low 64
  bits then the high 64, each in the host's byte order (little endian where ROS 2 runs);
- payload encoding: none set on the publisher or the put, i.e. Zenoh's default
  (`zenoh/bytes`), as rmw_zenoh_cpp publishes;
- discovery by liveliness tokens, a node's
  `@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>` and an
  endpoint's `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/<node>/
  <topic>/<type>/<hash>/<qos>`, with `/` written `%` inside a field and an empty field `%`.

CDR and the RIHS01 hashes come from `rosbags` (Apache-2.0), which carries the standard message
definitions of every distro: nothing is hand-written for the wire's payloads.
"""

from __future__ import annotations

import itertools
import struct
import time
from typing import Any

import xxhash
import zenoh

from keo_service.io.ros2_messages import typestore

__all__ = [
    "Ros2Node",
    "Ros2Publisher",
    "attachment",
    "data_key",
    "dds_type_name",
    "entity_gid",
    "mangle",
]

ATTACHMENT = struct.Struct("<qqB16s")
# reliable, volatile, keep last 10; rmw_zenoh leaves a field empty where it is the default
DEFAULT_QOS = "::,10:,:,:,,"


def dds_type_name(typename: str) -> str:
    """ "geometry_msgs/msg/PoseStamped" -> "geometry_msgs::msg::dds_::PoseStamped_"."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(store: Any, typename: str, distro: str) -> str:
    if distro == "humble":
        return "TypeHashNotSupported"
    return str(store.hash_rihs01(typename))


def data_key(domain: int, topic: str, typename: str, hash_: str) -> str:
    return f"{domain}/{topic.strip('/')}/{dds_type_name(typename)}/{hash_}"


def mangle(name: str) -> str:
    """A liveliness token field: `/` becomes `%`; empty (or the root namespace) is `%`."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def attachment(seq: int, source_ns: int, gid: bytes) -> bytes:
    return ATTACHMENT.pack(seq, source_ns, 16, gid)


def entity_gid(liveliness_key: str) -> bytes:
    """rmw_zenoh's gid of an entity: XXH3-128 of its liveliness token's key expression,
    low 64 bits first, each half little endian."""
    digest = xxhash.xxh3_128_intdigest(liveliness_key.encode())
    low, high = digest & 0xFFFF_FFFF_FFFF_FFFF, digest >> 64
    return low.to_bytes(8, "little") + high.to_bytes(8, "little")


class Ros2Publisher:
    """One ROS 2 publisher: CDR payload, attachment, and its liveliness token."""

    def __init__(self, node: Ros2Node, topic: str, typename: str, entity_id: int) -> None:
        self.typename = typename
        self._node = node
        self.key = data_key(node.domain, topic, typename, node.hash(typename))
        self._pub = node.session.declare_publisher(self.key, express=True)
        token = node.endpoint_token("MP", entity_id, topic, typename)
        self.gid = entity_gid(token)
        self._seq = itertools.count(1)
        self._token = node.session.liveliness().declare_token(token)

    def publish(self, message: Any, source_ns: int | None = None) -> None:
        payload = self._node.store.serialize_cdr(message, self.typename)
        stamp = time.time_ns() if source_ns is None else source_ns
        self._pub.put(bytes(payload), attachment=attachment(next(self._seq), stamp, self.gid))

    def close(self) -> None:
        self._token.undeclare()
        self._pub.undeclare()


class Ros2Node:
    """A ROS 2 node on a Zenoh session: its node token, publishers and subscriptions.

    Callers subscribe to `subscription_key` through keo's bounded hand-off
    (`AsyncSubscription`) and declare the subscription's token with `declare_subscription`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        domain: int = 0,
        distro: str = "jazzy",
        namespace: str = "/",
    ) -> None:
        self.session, self.name, self.domain, self.distro = session, name, domain, distro
        self.namespace = namespace
        self.store = typestore(distro)
        self.zid = str(session.zid())
        self.node_id = 0
        self._entity_ids = itertools.count(1)
        self._hashes: dict[str, str] = {}
        self._closables: list[Any] = []
        self._token = session.liveliness().declare_token(
            f"@ros2_lv/{domain}/{self.zid}/{self.node_id}/{self.node_id}/NN/%/"
            f"{mangle(namespace)}/{name}"
        )

    def hash(self, typename: str) -> str:
        if typename not in self._hashes:
            self._hashes[typename] = type_hash(self.store, typename, self.distro)
        return self._hashes[typename]

    def endpoint_token(self, kind: str, entity_id: int, topic: str, typename: str) -> str:
        return (
            f"@ros2_lv/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/%/"
            f"{mangle(self.namespace)}/{self.name}/{mangle(topic)}/{dds_type_name(typename)}/"
            f"{self.hash(typename)}/{DEFAULT_QOS}"
        )

    def publisher(self, topic: str, typename: str) -> Ros2Publisher:
        pub = Ros2Publisher(self, topic, typename, next(self._entity_ids))
        self._closables.append(pub)
        return pub

    def subscription_key(self, topic: str, typename: str) -> str:
        """The data key of a topic, any type hash (a Humble publisher writes none)."""
        return f"{self.domain}/{topic.strip('/')}/{dds_type_name(typename)}/*"

    def declare_subscription(self, topic: str, typename: str) -> None:
        """The subscription's liveliness token (the data itself is subscribed by the caller
        on `subscription_key`, through keo's bounded hand-off)."""
        token = self.session.liveliness().declare_token(
            self.endpoint_token("MS", next(self._entity_ids), topic, typename)
        )
        self._closables.append(token)

    def deserialize(self, payload: bytes, typename: str) -> Any:
        return self.store.deserialize_cdr(payload, typename)

    def close(self) -> None:
        for item in reversed(self._closables):
            if isinstance(item, Ros2Publisher):
                item.close()
            else:
                item.undeclare()
        self._closables.clear()
        self._token.undeclare()
