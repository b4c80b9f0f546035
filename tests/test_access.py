"""Access control on the bus: the rights table docs/design.md §6 gives each role, as the Zenoh
`access_control` section keo builds, and the config errors around it. The end-to-end test
with real certificates and processes is tests/test_access_e2e.py."""

from __future__ import annotations

import json

import msgspec
import pytest
import zenoh

from keo_service.core.errors import ConfigError
from keo_service.io.config import load_config
from keo_service.live.access import access_control, access_control_for
from keo_service.live.bus import make_zenoh_config
from tests.conftest import write_config

ROLES = {
    "enc.c1": "encoder",
    "trk.c1": "tracker",
    "svc.c1": "service",
    "hmi.c1": "client",
    "alice": "operator",
    "bob": "client",
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
