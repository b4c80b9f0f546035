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

Every keo session applies them. A link only shows Zenoh the certificate at its other end, so a
sample relayed by a hub (`keo router`, or the service when it listens) arrives at a leaf as the
hub's: the hub judges each identity, and a leaf judges its hub. Hence the relay roles: the
`router` role (a router's certificate) may put and subscribe to everything everywhere, and on a
leaf (`hub=False`: adapters, clients, echo, record, a service behind a router) the `service`
role is a relay too, since a leaf that reaches the service directly has it as its hub. A hub
judges a service that connects to it by the table. A direct link to an identity with any other
role is judged by that role on both sides, so a client-role peer cannot put anything even where
no hub is in between.

A leaf also knows its own role (its certificate's common name in [bus.roles]) and sends only
what that role may put: its egress data rules to each remote are the keys both its own role
may put and the remote may receive. A hub cannot do this (what it sends is mostly relayed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from keo_service.core.errors import ConfigError

ROLES = ("encoder", "tracker", "service", "client", "operator", "router")

# the roles a leaf takes everything from: what its hub sends was put by anyone
RELAYS = ("router", "service", "operator")

# everything, on every key (`**` does not reach the `@`-prefixed ROS 2 liveliness keys)
EVERYTHING = ["**", "@ros2_lv/**"]

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
        "operator": (EVERYTHING, EVERYTHING),
        # a hub: whatever it passes on was put by an identity it has judged
        "router": (EVERYTHING, EVERYTHING),
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


def common_name(config: Any) -> str:
    """The common name of this node's own certificate (bus.tls_certificate, PEM)."""
    path = config.bus.tls_certificate
    try:
        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    except (OSError, ValueError) as exc:
        raise ConfigError(
            config.source or "<config>", "bus.tls_certificate", f"cannot read {path}: {exc}"
        ) from None
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def within(keys: list[str], allowed: list[str]) -> list[str]:
    """The part of `keys` inside `allowed`, as key expressions: each key an allowed one
    includes, and each allowed key inside one of `keys`. Two that only overlap give nothing
    (denied: narrower than the truth, never wider)."""
    out: list[str] = []
    for k in keys:
        for a in allowed:
            ka, kk = zenoh.KeyExpr(a), zenoh.KeyExpr(k)
            part = k if ka.includes(kk) else a if kk.includes(ka) else None
            if part is not None and part not in out:
                out.append(part)
    return out


def access_control(config: Any, hub: bool = True, own_role: str | None = None) -> dict[str, Any]:
    """Zenoh's `access_control` section (JSON-able) for `config`: default deny, one subject per
    role holding the common names [bus.roles] gives it, the rules of `rights`. `hub`: the
    session others connect to and that relays between them (`keo router`, a listening
    service); False for a leaf, which takes what the `service` role relays to it and sends
    data only on keys its `own_role` may put (none when it has no role)."""
    table = rights(config)
    own_put = table[own_role][0] if own_role in table else []
    if not hub:  # (after own_put: a service behind a router puts only its own keys)
        table["service"] = (EVERYTHING, EVERYTHING)
    cell_keys = f"keo/{config.cell}/**"
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        names = sorted(cn for cn, r in config.bus.roles.items() if r == role)
        if not names:
            continue
        put_keys, sub_keys = table[role]
        sent = sub_keys if hub else within(own_put, sub_keys)
        ids = []
        for flow, messages, keys in (
            ("ingress", PUT_SIDE, put_keys),
            ("ingress", SUBSCRIBE_SIDE, sub_keys),
            ("egress", PUT_SIDE, sent),
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


def access_control_for(config: Any, hub: bool = True) -> dict[str, Any] | None:
    """The section when [bus] asks for access control, else None. A leaf's own role comes
    from its certificate's common name."""
    if not config.bus.access_control:
        return None
    cn = common_name(config)
    own_role = config.bus.roles.get(cn)
    if hub and own_role not in RELAYS:
        raise ConfigError(
            config.source or "<config>",
            "bus.roles",
            f"this node relays for the others (a router, or the service listening), but its "
            f"certificate's common name {cn!r} has "
            + (f"the role {own_role!r}" if own_role else "no role")
            + ": the leaves take relayed samples only from "
            + ", ".join(repr(r) for r in RELAYS)
            + ' (give a router "router")',
        )
    return access_control(config, hub, None if hub else own_role)
