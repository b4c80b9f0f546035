"""Access control on the bus: the rights table docs/design.md §6 gives each role, as the Zenoh
`access_control` section keo builds, and the config errors around it. The end-to-end test
with real certificates and processes is tests/test_access_e2e.py."""

from __future__ import annotations

import json
import subprocess

import msgspec
import pytest
import zenoh

from keo_service.core.errors import ConfigError
from keo_service.io.config import load_config
from keo_service.live.access import access_control, access_control_for, common_name, within
from keo_service.live.bus import make_zenoh_config
from tests.conftest import write_config

ROLES = {
    "enc.c1": "encoder",
    "trk.c1": "tracker",
    "svc.c1": "service",
    "hmi.c1": "client",
    "alice": "operator",
    "bob": "client",
    "hub.c1": "router",
}

PUT = {"put", "delete", "reply", "declare_queryable", "liveliness_token"}
SUB = {"declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"}


def _config(tmp_path, extra: str = "", roles=ROLES):
    body = 'cell = "c1"\n[robot]\nurdf = "@ROBOTS@/mh180.urdf"\n' + extra
    config = load_config(write_config(tmp_path, body))
    bus = msgspec.structs.replace(config.bus, roles=dict(roles), access_control=True)
    return msgspec.structs.replace(config, bus=bus)


def _allowed(acl, role: str, flow: str, kinds: set[str]) -> set[str]:
    """Key expressions a role's subject is allowed for `kinds` on `flow`."""
    by_id = {r["id"]: r for r in acl["rules"]}
    keys: set[str] = set()
    for policy in acl["policies"]:
        if role not in policy["subjects"]:
            continue
        for rule_id in policy["rules"]:
            rule = by_id[rule_id]
            assert rule["permission"] == "allow"
            if flow in rule["flows"] and kinds <= set(rule["messages"]):
                keys |= set(rule["key_exprs"])
            else:
                assert not (kinds & set(rule["messages"])) or flow not in rule["flows"]
    return keys


# docs/design.md §6, written out by hand for cell "c1" without ROS 2
EXPECTED = {
    "encoder": ({"keo/c1/encoder", "keo/c1/robot_status", "keo/c1/adapter/encoder/**"}, set()),
    "tracker": ({"keo/c1/tracker", "keo/c1/adapter/tracker/**"}, set()),
    "service": (
        {"keo/c1/estimate", "keo/c1/correction", "keo/c1/status", "keo/c1/alive/**"},
        {"keo/c1/**"},
    ),
    "client": (set(), {"keo/c1/**"}),
    "operator": ({"**", "@ros2_lv/**"}, {"**", "@ros2_lv/**"}),
    "router": ({"**", "@ros2_lv/**"}, {"**", "@ros2_lv/**"}),
}


@pytest.mark.parametrize("role", sorted(EXPECTED))
def test_each_role_gets_the_design_rights_both_ways(tmp_path, role):
    acl = access_control(_config(tmp_path))
    may_put, may_sub = EXPECTED[role]
    # what a remote of this role may send us
    assert _allowed(acl, role, "ingress", PUT) == may_put
    assert _allowed(acl, role, "ingress", SUB) == may_sub
    # what we may send it: data it may subscribe to, interest in what it publishes
    assert _allowed(acl, role, "egress", PUT) == may_sub
    # (a subscriber on keo/c1/* must reach the encoder: interest covers the cell's keys)
    interest = may_put | {"keo/c1/**"} if may_put and "**" not in may_put else may_put
    assert _allowed(acl, role, "egress", SUB) == interest


def test_default_deny_and_subjects_by_common_name(tmp_path):
    acl = access_control(_config(tmp_path))
    assert acl["enabled"] is True
    assert acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])
    names = {s["id"]: set(s["cert_common_names"]) for s in acl["subjects"]}
    assert names == {
        "encoder": {"enc.c1"},
        "tracker": {"trk.c1"},
        "service": {"svc.c1"},
        "client": {"hmi.c1", "bob"},
        "operator": {"alice"},
        "router": {"hub.c1"},
    }
    # nobody but the operator may put an encoder sample or a correction
    for role in ("tracker", "service", "client"):
        assert "keo/c1/encoder" not in _allowed(acl, role, "ingress", PUT)
    for role in ("encoder", "tracker", "client"):
        assert not {"keo/c1/correction", "keo/c1/**"} & _allowed(acl, role, "ingress", PUT)


def test_a_role_nobody_holds_has_no_subject(tmp_path):
    acl = access_control(_config(tmp_path, roles={"svc": "service"}))
    assert [s["id"] for s in acl["subjects"]] == ["service"]
    assert {p["id"] for p in acl["policies"]} == {"service"}


def test_ros2_keys_join_the_table_when_ros2_is_on(tmp_path):
    extra = "[ros2]\nenabled = true\ndomain_id = 7\n"
    acl = access_control(_config(tmp_path, extra))
    service_put = _allowed(acl, "service", "ingress", PUT)
    assert {"7/keo/c1/**", "7/tf/**", "@ros2_lv/7/**"} <= service_put
    assert {"7/**", "@ros2_lv/7/**", "keo/c1/**"} == _allowed(acl, "client", "ingress", SUB)
    assert _allowed(acl, "client", "ingress", PUT) == set()


def test_a_ros2_encoder_may_subscribe_to_its_joint_states_only(tmp_path):
    body = (
        'cell = "c1"\n[robot]\nurdf = "@ROBOTS@/mh180.urdf"\nprotocol = "ros2"\n'
        'joint_states_topic = "/arm/joint_states"\n'
    )
    config = load_config(write_config(tmp_path, body))
    config = msgspec.structs.replace(
        config, bus=msgspec.structs.replace(config.bus, roles=ROLES, access_control=True)
    )
    acl = access_control(config)
    assert _allowed(acl, "encoder", "ingress", SUB) == {"0/arm/joint_states/**", "@ros2_lv/0/**"}
    assert _allowed(acl, "tracker", "ingress", SUB) == set()


def test_zenoh_accepts_the_section(tmp_path):
    acl = access_control(_config(tmp_path, "[ros2]\nenabled = true\n"))
    cfg = make_zenoh_config("peer", access=acl)
    assert json.loads(cfg.get_json("access_control"))["default_permission"] == "deny"
    session = zenoh.open(cfg)  # zenoh validates the rules, subjects and policies on open
    session.close()


def test_off_by_default(tmp_path):
    body = 'cell = "c1"\n[robot]\nurdf = "@ROBOTS@/mh180.urdf"\n'
    config = load_config(write_config(tmp_path, body))
    assert access_control_for(config) is None


@pytest.mark.parametrize(
    ("bus", "key"),
    [
        ('access_control = true\n[bus.roles]\n"a" = "client"\n', "bus.access_control"),
        (
            'access_control = true\ntls_mtls = true\ntls_certificate = "@CERT@"\n'
            'tls_private_key = "@CERT@"\ntls_root_ca = "@CERT@"\nlisten = ["tls/localhost:1"]\n',
            "bus.roles",
        ),
        ('[bus.roles]\n"a" = "admin"\n', "bus.roles"),
        (
            'access_control = true\ntls_mtls = true\ntls_certificate = "@CERT@"\n'
            'tls_private_key = "@CERT@"\ntls_root_ca = "@CERT@"\n[bus.roles]\n"a" = "client"\n',
            "bus.listen",
        ),
    ],
)
def test_config_errors_name_the_key(tmp_path, bus, key):
    cert = tmp_path / "x.pem"
    cert.write_text("x")
    body = 'cell = "c1"\n[robot]\nurdf = "@ROBOTS@/mh180.urdf"\n[bus]\n' + bus
    with pytest.raises(ConfigError) as info:
        load_config(write_config(tmp_path, body.replace("@CERT@", str(cert))))
    assert key in str(info.value)


def test_an_encoder_that_writes_corrections_may_read_them(tmp_path):
    """With `robot.correction` set, the encoder adapter subscribes to keo/<cell>/correction
    to write it to its controller; without it, the encoder reads nothing of keo's."""
    acl = access_control(_config(tmp_path, 'protocol = "rtde"\ncorrection = "rtde_registers"\n'))
    assert _allowed(acl, "encoder", "ingress", SUB) == {"keo/c1/correction"}
    assert _allowed(acl, "tracker", "ingress", SUB) == set()


ALL = {"**", "@ros2_lv/**"}
ENCODER_PUT = EXPECTED["encoder"][0]


def test_on_a_leaf_the_hub_relays_and_direct_peers_are_judged_by_role(tmp_path):
    """A leaf's only remote in client mode is its hub, which passes on what others put: the
    router role and (on a leaf) the service role may send it anything. Any other identity
    linked to it directly is held to the table, as on a hub."""
    config = _config(tmp_path)
    leaf, hub = access_control(config, hub=False), access_control(config, hub=True)
    for role in ("router", "service"):
        assert _allowed(leaf, role, "ingress", PUT) == ALL
        assert _allowed(leaf, role, "ingress", SUB) == ALL
    assert _allowed(hub, "router", "ingress", PUT) == ALL
    assert _allowed(hub, "service", "ingress", PUT) == EXPECTED["service"][0]
    for role in ("encoder", "tracker", "client", "operator"):
        assert _allowed(leaf, role, "ingress", PUT) == EXPECTED[role][0]
        assert _allowed(leaf, role, "ingress", SUB) == EXPECTED[role][1]
    assert _allowed(leaf, "client", "ingress", PUT) == set()


def test_a_leaf_sends_only_what_its_own_role_may_put(tmp_path):
    config = _config(tmp_path)
    client = access_control(config, hub=False, own_role="client")
    unknown = access_control(config, hub=False, own_role=None)
    for acl in (client, unknown):
        for role in EXPECTED:
            assert _allowed(acl, role, "egress", PUT) == set(), role
    encoder = access_control(config, hub=False, own_role="encoder")
    for role in ("router", "service", "client", "operator"):
        assert _allowed(encoder, role, "egress", PUT) == ENCODER_PUT, role
    assert _allowed(encoder, "tracker", "egress", PUT) == set()
    # a service behind a router puts its own keys, not everything its hub may relay
    service = access_control(config, hub=False, own_role="service")
    assert _allowed(service, "router", "egress", PUT) == EXPECTED["service"][0]
    assert _allowed(service, "encoder", "egress", PUT) == set()
    operator = access_control(config, hub=False, own_role="operator")
    assert _allowed(operator, "router", "egress", PUT) == ALL
    assert _allowed(operator, "client", "egress", PUT) == {"keo/c1/**"}


def test_a_leaf_sends_corrections_only_to_an_encoder_that_reads_them(tmp_path):
    extra = 'protocol = "rtde"\ncorrection = "rtde_registers"\n'
    acl = access_control(_config(tmp_path, extra), hub=False, own_role="service")
    assert _allowed(acl, "encoder", "egress", PUT) == {"keo/c1/correction"}


def test_within_keeps_the_common_part_and_drops_mere_overlaps():
    assert within(["keo/c1/encoder", "keo/c2/encoder"], ["keo/c1/**"]) == ["keo/c1/encoder"]
    assert within(["**"], ["keo/c1/**", "@ros2_lv/0/**"]) == ["keo/c1/**"]
    assert within(["**", "@ros2_lv/**"], ["@ros2_lv/0/**"]) == ["@ros2_lv/0/**"]
    # they meet at keo/c1/encoder, and neither holds the other: nothing (denied)
    assert within(["keo/*/encoder"], ["keo/c1/**"]) == []
    assert within([], ["**"]) == []


def _certificate(directory, cn: str):
    subprocess.run(
        [
            "openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-days", "1", "-subj", f"/CN={cn}/O=keo test", "-keyout", "k.pem",
            "-out", "c.pem",
        ],
        check=True, capture_output=True, cwd=directory,
    )  # fmt: skip
    return directory / "c.pem"


def test_a_leaf_takes_its_own_role_from_its_certificate(tmp_path):
    config = _config(tmp_path)
    cert = _certificate(tmp_path, "enc.c1")
    config = msgspec.structs.replace(
        config, bus=msgspec.structs.replace(config.bus, tls_certificate=str(cert))
    )
    assert common_name(config) == "enc.c1"
    leaf = access_control_for(config, hub=False)
    assert leaf is not None
    assert _allowed(leaf, "router", "egress", PUT) == ENCODER_PUT
    # a hub relays: what it sends is judged by the receiver's role only
    assert _allowed(access_control(config, hub=True), "router", "egress", PUT) == ALL


def test_an_unreadable_certificate_is_a_config_error(tmp_path):
    config = _config(tmp_path)
    bad = tmp_path / "bad.pem"
    bad.write_text("not a certificate")
    config = msgspec.structs.replace(
        config, bus=msgspec.structs.replace(config.bus, tls_certificate=str(bad))
    )
    with pytest.raises(ConfigError, match=r"bus\.tls_certificate"):
        access_control_for(config, hub=False)


@pytest.mark.parametrize(("cn", "ok"), [("hub.c1", True), ("svc.c1", True), ("hmi.c1", False)])
def test_a_hub_needs_a_role_the_leaves_take_relayed_samples_from(tmp_path, cn, ok):
    """With a client's (or no) role on a router's certificate every leaf would refuse all it
    relays: a config error naming bus.roles, at start."""
    config = _config(tmp_path)
    cert = _certificate(tmp_path, cn)
    config = msgspec.structs.replace(
        config, bus=msgspec.structs.replace(config.bus, tls_certificate=str(cert))
    )
    if ok:
        assert access_control_for(config, hub=True) is not None
    else:
        with pytest.raises(ConfigError, match=r"bus\.roles.*'hmi\.c1' has the role 'client'"):
            access_control_for(config, hub=True)
