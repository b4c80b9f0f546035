"""Who may put what on the bus: Zenoh's `access_control` configuration built from [bus].

docs/design.md §6 gives each role the keys it may put (or reply on) and the keys it may subscribe
to (or query). Zenoh matches a rule's subject against the REMOTE side's mTLS certificate
common name on each link and enforces the rules on the node that has them configured, on
that node's ingress and egress. So the rules here describe, for a remote of role R:

- ingress from R: R's put side (put, delete, reply, declare_queryable, liveliness_token) on
  the keys R may put, R's subscribe side (declare_subscriber, query, liveliness subscriber and
  query) on the keys R may subscribe to;
- egress to R: data (puts, replies, queryables, liveliness tokens) only on keys R may
  subscribe to, and interest (subscribers, queries) on the keys R publishes and the cell's
  keys (see `_interest`).

Anything else is denied (`default_permission = "deny"`), including every certificate common
name that is not in [bus.roles].

The nodes others connect to enforce it: `keo router` and the service when it listens (peer
mode). A leaf session (adapter, client, echo, record) has one remote, its hub, which relays
other identities' samples; on the leaf the sample's origin is no longer visible, so rules
there could only repeat the hub's decision or wrongly refuse what the hub relays.
"""

from __future__ import annotations

from typing import Any

ROLES = ("encoder", "tracker", "service", "client", "operator")

# what a remote that publishes sends, and what one that subscribes sends
PUT_SIDE = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
SUBSCRIBE_SIDE = [
    "declare_subscriber",
    "query",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


def rights(config: Any) -> dict[str, tuple[list[str], list[str]]]:
    """Role -> (keys it may put / reply on, keys it may subscribe to / query), docs/design.md §6."""
    cell = config.cell
    keo = f"keo/{cell}"
    ros = config.ros2
    ros_on = bool(ros.enabled) or "ros2" in (config.robot.protocol, config.tracker.protocol)
    domain = ros.domain_id
    ros_tokens = [f"@ros2_lv/{domain}/**"] if ros_on else []
    encoder_in = (
        [f"{domain}/{config.robot.joint_states_topic.strip('/')}/**"]
        if config.robot.protocol == "ros2"
        else []
    )
    tracker_in = (
        [f"{domain}/{config.tracker.pose_topic.strip('/')}/**"]
        if config.tracker.protocol == "ros2"
        else []
    )
    # an encoder adapter that writes live corrections to its controller reads them from the bus
    corrections_in = [f"{keo}/correction"] if config.robot.correction != "none" else []
    service_ros = [f"{domain}/keo/{cell}/**", f"{domain}/tf/**"] if ros.enabled else []
    return {
        "encoder": (
            [f"{keo}/encoder", f"{keo}/robot_status", f"{keo}/adapter/encoder/**", *ros_tokens],
            encoder_in + (ros_tokens if encoder_in else []) + corrections_in,
        ),
        "tracker": (
            [f"{keo}/tracker", f"{keo}/adapter/tracker/**", *ros_tokens],
            tracker_in + (ros_tokens if tracker_in else []),
        ),
        "service": (
            [
                f"{keo}/estimate",
                f"{keo}/correction",
                f"{keo}/status",
                f"{keo}/alive/**",
                *service_ros,
                *ros_tokens,
            ],
            [f"{keo}/**"],
        ),
        "client": ([], [f"{keo}/**", *([f"{domain}/**"] if ros_on else []), *ros_tokens]),
        "operator": (["**", "@ros2_lv/**"], ["**", "@ros2_lv/**"]),
    }


def _interest(put_keys: list[str], cell_keys: str) -> list[str]:
    """Interest sent to a publishing identity. A subscriber on `keo/<cell>/*` (the service's)
    is not inside `keo/<cell>/encoder`, and Zenoh checks a declaration's whole key
    expression: without the cell's keys here the encoder would never learn that anyone
    listens, and its client session would drop its own samples. Interest carries no data;
    what the identity may send back is limited by the ingress rules."""
    if not put_keys:
        return []
    return put_keys if any(k in ("**", cell_keys) for k in put_keys) else [*put_keys, cell_keys]


def access_control(config: Any) -> dict[str, Any]:
    """Zenoh's `access_control` section (JSON-able) for `config`: default deny, one subject per
    role holding the common names [bus.roles] gives it, the rules of `rights`."""
    table = rights(config)
    cell_keys = f"keo/{config.cell}/**"
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        names = sorted(cn for cn, r in config.bus.roles.items() if r == role)
        if not names:
            continue
        put_keys, sub_keys = table[role]
        ids = []
        for flow, messages, keys in (
            ("ingress", PUT_SIDE, put_keys),
            ("ingress", SUBSCRIBE_SIDE, sub_keys),
            ("egress", PUT_SIDE, sub_keys),
            ("egress", SUBSCRIBE_SIDE, _interest(put_keys, cell_keys)),
        ):
            if not keys:
                continue
            side = "put" if messages is PUT_SIDE else "subscribe"
            rule_id = f"{role}-{flow}-{side}"
            rules.append(
                {
                    "id": rule_id,
                    "permission": "allow",
                    "flows": [flow],
                    "messages": list(messages),
                    "key_exprs": list(keys),
                }
            )
            ids.append(rule_id)
        subjects.append({"id": role, "cert_common_names": names})
        if ids:
            policies.append({"id": role, "rules": ids, "subjects": [role]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def access_control_for(config: Any) -> dict[str, Any] | None:
    """The section when [bus] asks for access control, else None."""
    return access_control(config) if config.bus.access_control else None
