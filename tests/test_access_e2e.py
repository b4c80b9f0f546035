"""Access control with real certificates and processes: every keo session (`keo run`,
`keo router`, the adapters, clients) enforces the rights of docs/design.md §6 by mTLS
certificate common name. A client identity that puts encoder samples or corrections is
refused, through a hub or linked straight to another peer, while the legitimate encoder and
tracker keep the service estimating with rules on every session; the client may still
subscribe to estimates and query status; a certificate from another CA does not connect."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
import zenoh

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import free_port, process_group
from keo_service.core.errors import KeoError
from keo_service.io.config import config_to_toml, load_config
from keo_service.live.bus import (
    BlockingSubscription,
    leaf_access,
    open_session,
    session_for_client,
)
from keo_service.live.client import SyncClient
from keo_service.live.messages import (
    CorrectionMessage,
    EstimateMessage,
    JointSample,
    ServiceStatus,
    TrackerSample,
    decode,
    encode,
    topic,
)
from keo_service.live.recorder import replay_plan
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import keo

pytestmark = pytest.mark.e2e

ROLES = {
    "router.demo": "router",
    "svc.demo": "service",
    "enc.demo": "encoder",
    "trk.demo": "tracker",
    "hmi.demo": "client",
    "watch.demo": "operator",
}
ROGUE_SEQ = 1_000_000


def make_pki(directory: Path, ca: str, names: list[str]) -> None:
    """A CA and a certificate per name (CN = name), EC P-256, made with the openssl CLI."""

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=directory)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    run("req", "-x509", *ec, "-days", "2", "-subj", f"/CN={ca}", "-keyout", f"{ca}.key")
    run(
        "req", "-x509", "-key", f"{ca}.key", "-days", "2", "-subj", f"/CN={ca}", "-out", f"{ca}.pem"
    )
    ext = directory / "leaf.ext"
    ext.write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n")
    for name in names:
        run("req", *ec, "-subj", f"/CN={name}", "-keyout", f"{name}.key", "-out", f"{name}.csr")
        run(
            "x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
            "-CAcreateserial", "-days", "2", "-out", f"{name}.pem", "-extfile", "leaf.ext",
        )  # fmt: skip


def write_identity(demo_config, tmp: Path, pki: Path, ca: str, name: str, **bus) -> Path:
    settings = {
        "tls_root_ca": str(pki / f"{ca}.pem"),
        "tls_certificate": str(pki / f"{name}.pem"),
        "tls_private_key": str(pki / f"{name}.key"),
        "tls_mtls": True,
        "access_control": True,
        "roles": ROLES,
        **bus,
    }
    config = msgspec.structs.replace(
        demo_config, bus=msgspec.structs.replace(demo_config.bus, **settings)
    )
    path = tmp / f"{name}.toml"
    path.write_text(config_to_toml(config))
    return path


def _status(session: zenoh.Session) -> ServiceStatus | None:
    for reply in session.get(topic("demo", "status"), timeout=2.0):
        if reply.ok is not None:
            try:  # the service answers with nothing until it has a status
                msg = decode(reply.ok.payload.to_bytes())
            except msgspec.DecodeError:
                continue
            if isinstance(msg, ServiceStatus):
                return msg
    return None


@pytest.mark.parametrize("hub", ["service", "router"])
def test_rights_by_certificate(demo_config, demo_cell, tmp_path, hub):
    pki = tmp_path / "pki"
    pki.mkdir()
    make_pki(pki, "keo-ca", list(ROLES))
    make_pki(pki, "other-ca", ["enc.other"])  # a stranger's CA and a certificate it signed
    endpoint = f"tls/localhost:{free_port()}"
    leaf = {"mode": "client", "listen": [], "connect": [endpoint]}
    service_bus = leaf if hub == "router" else {"mode": "peer", "listen": [endpoint]}
    cfg = {
        name: write_identity(demo_config, tmp_path, pki, "keo-ca", name, **leaf)
        for name in ROLES
        if name not in ("svc.demo", "router.demo")
    }
    cfg["svc.demo"] = write_identity(
        demo_config, tmp_path, pki, "keo-ca", "svc.demo", **service_bus
    )
    router = write_identity(demo_config, tmp_path, pki, "keo-ca", "router.demo", **leaf)
    # the stranger's certificate even carries a legitimate common name
    stranger = write_identity(demo_config, tmp_path, pki, "other-ca", "enc.other", **leaf)

    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3"}), seed=5)
    plan = replay_plan(run.encoder.t, run.tracker.t)
    with process_group(tmp_path) as procs:
        if hub == "router":
            procs.start("router", ["router", "--listen", endpoint, "--config", str(router)])
        procs.start("service", ["run", "--config", str(cfg["svc.demo"])])
        sessions = {
            name: session_for_client(load_config(cfg[name]), retry_for=20.0)
            for name in ("enc.demo", "trk.demo", "hmi.demo", "watch.demo")
        }
        try:
            hmi, watch = sessions["hmi.demo"], sessions["watch.demo"]
            deadline = time.monotonic() + 20
            while _status(hmi) is None:  # a client may query status
                assert time.monotonic() < deadline, procs.log("service")
            watched = BlockingSubscription(watch, "keo/demo/**")
            estimates = BlockingSubscription(hmi, topic("demo", "estimate"))
            time.sleep(0.5)  # subscriptions reach the hub
            block = zenoh.CongestionControl.BLOCK
            enc = sessions["enc.demo"].declare_publisher(
                "keo/demo/encoder", congestion_control=block
            )
            trk = sessions["trk.demo"].declare_publisher(
                "keo/demo/tracker", congestion_control=block
            )
            rogue_enc = hmi.declare_publisher("keo/demo/encoder", congestion_control=block)
            rogue_corr = hmi.declare_publisher("keo/demo/correction", congestion_control=block)
            sent = rogue = 0
            for k in range(plan.t.size):
                i = int(plan.index[k])
                now = time.time_ns()
                if plan.kinds[k] == 0:
                    q = run.encoder.q[i].tolist()
                    enc.put(
                        encode(
                            JointSample(
                                stamp=float(run.encoder.t[i]), host_ns=now, seq=i + 1, joints=q
                            )
                        )
                    )
                    # the client identity puts a sample of its own, and a correction
                    bad = [x + 0.5 for x in q]
                    rogue_enc.put(
                        encode(
                            JointSample(
                                stamp=float(run.encoder.t[i]),
                                host_ns=now,
                                seq=ROGUE_SEQ + i,
                                joints=bad,
                            )
                        )
                    )
                    zero = [0.0, 0.0, 0.0]
                    rogue_corr.put(
                        encode(
                            CorrectionMessage(
                                stamp=0.0,
                                host_ns=now,
                                seq=i,
                                translation=[0.01, 0, 0],
                                rotation=zero,
                                feedback_translation=zero,
                                feedback_rotation=zero,
                                feedforward_translation=zero,
                                feedforward_rotation=zero,
                                valid=True,
                            )
                        )
                    )
                    rogue += 2
                else:
                    p, quat = run.tracker.p[i].tolist(), run.tracker.quat[i].tolist()
                    trk.put(
                        encode(
                            TrackerSample(
                                stamp=float(run.tracker.t[i]),
                                host_ns=now,
                                seq=i + 1,
                                position=p,
                                quaternion=quat,
                            )
                        )
                    )
                sent += 1
                if k % 20 == 0:
                    time.sleep(0.01)
            # the service took every legitimate sample and nothing of the client's
            deadline = time.monotonic() + 20
            status = _status(hmi)
            while status is None or status.counters["received"] < sent:
                assert time.monotonic() < deadline, (
                    status and status.counters,
                    sent,
                    procs.log("service"),
                )
                time.sleep(0.2)
                status = _status(hmi)
            time.sleep(0.5)
            status = _status(hmi)
            assert status is not None
            assert status.counters["received"] == sent, status.counters
            assert status.counters["published"] > 50, status.counters
            # what the operator sees on the bus: the encoder's samples, none of the client's
            seen: dict[str, list[object]] = {}
            while (item := watched.get(timeout=0.5)) is not None:
                seen.setdefault(item[0], []).append(decode(item[1]))
            encoder_seqs = [
                m.seq for m in seen.get("keo/demo/encoder", []) if isinstance(m, JointSample)
            ]
            assert len(encoder_seqs) == run.encoder.t.size
            assert max(encoder_seqs) < ROGUE_SEQ
            # the service publishes corrections of its own (stamped on the stream's clock);
            # none of the client's (stamp 0, 10 mm along x) gets through
            rogue_seen = [
                m
                for m in seen.get("keo/demo/correction", [])
                if isinstance(m, CorrectionMessage) and m.stamp == 0.0 and m.translation[0] == 0.01
            ]
            assert rogue_seen == []
            assert len(seen.get("keo/demo/estimate", [])) > 50
            # the client identity still subscribes to estimates
            got = 0
            while (item := estimates.get(timeout=0.5)) is not None:
                got += isinstance(decode(item[1]), EstimateMessage)
            assert got > 50
            assert rogue > 100
        finally:
            for session in sessions.values():
                session.close()
        # another CA's certificate: the TLS handshake fails, nothing connects
        with pytest.raises(KeoError, match="cannot reach the bus"):
            session_for_client(load_config(stranger), retry_for=2.0)
        assert procs.procs["service"].poll() is None, procs.log("service")


# A peer process: opens a keo session in peer mode straight to `endpoint` under the identity
# of its config, with the leaf's rules ("rules") or none, and puts `n` encoder samples and `n`
# corrections whose seq starts at `base`.
PEER = """
import sys, time
import zenoh
from keo_service.io.config import load_config
from keo_service.live.bus import leaf_access, open_session
from keo_service.live.messages import CorrectionMessage, JointSample, encode
path, endpoint, rules, base, n = sys.argv[1:6]
config = load_config(path)
access = leaf_access(config) if rules == "rules" else None
session = open_session("peer", connect=[endpoint], tls=config.bus, access=access)
block = zenoh.CongestionControl.BLOCK
enc = session.declare_publisher("keo/demo/encoder", congestion_control=block)
corr = session.declare_publisher("keo/demo/correction", congestion_control=block)
# until the other side's subscriber reaches us (never, where its rules hide it from us)
deadline = time.monotonic() + 3.0
while not enc.matching_status.matching and time.monotonic() < deadline:
    time.sleep(0.05)
time.sleep(0.2)
zero = [0.0, 0.0, 0.0]
for i in range(int(base), int(base) + int(n)):
    enc.put(encode(JointSample(stamp=i * 0.01, host_ns=time.time_ns(), seq=i, joints=[0.5] * 6)))
    corr.put(encode(CorrectionMessage(stamp=0.0, host_ns=time.time_ns(), seq=i,
        translation=[0.01, 0.0, 0.0], rotation=zero, feedback_translation=zero,
        feedback_rotation=zero, feedforward_translation=zero, feedforward_rotation=zero,
        valid=True)))
time.sleep(0.5)
session.close()
"""


def _listening(watch, access, tries: int = 3):
    """A peer session listening on a free loopback port, with another port if one was taken
    between asking and binding: a zenoh session's outgoing links take ephemeral ports from
    the same range (CI saw "Address already in use" once)."""
    for attempt in range(tries):
        endpoint = f"tls/localhost:{free_port()}"
        try:
            return endpoint, open_session("peer", [endpoint], tls=watch.bus, access=access)
        except zenoh.ZError as exc:
            if "Address already in use" not in str(exc) or attempt == tries - 1:
                raise
    raise AssertionError("unreachable")


def test_a_client_peer_linked_directly_cannot_put(demo_config, tmp_path):
    """No hub in between: peer processes link straight to a listening keo session and put
    encoder samples and corrections. The encoder identity's samples arrive; a client
    identity's are refused by the receiver's rules alone (the rogue runs without keo's
    rules) and by the client's own session alone (the receiver has no rules), and get
    through only when neither side has rules."""
    pki = tmp_path / "pki"
    pki.mkdir()
    make_pki(pki, "keo-ca", ["enc.demo", "hmi.demo", "watch.demo"])
    leaf = {"mode": "peer", "listen": [], "connect": []}
    cfg = {
        name: write_identity(demo_config, tmp_path, pki, "keo-ca", name, **leaf)
        for name in ("enc.demo", "hmi.demo", "watch.demo")
    }
    watch = load_config(cfg["watch.demo"])
    # two listening leaves with the operator's certificate: one with keo's rules, one without
    guarded, guarded_session = _listening(watch, leaf_access(watch))
    open_, open_session_ = _listening(watch, None)
    receivers = {guarded: guarded_session, open_: open_session_}
    subs = {ep: BlockingSubscription(s, "keo/demo/**") for ep, s in receivers.items()}
    n = 40
    runs = {  # seq base -> (identity, endpoint, rules on the putting side)
        1000: ("enc.demo", guarded, "rules"),
        2000: ("hmi.demo", guarded, "rules"),
        3000: ("hmi.demo", guarded, "none"),
        4000: ("hmi.demo", open_, "rules"),
        5000: ("hmi.demo", open_, "none"),
    }
    try:
        procs = [
            subprocess.Popen(
                [sys.executable, "-c", PEER, str(cfg[name]), ep, rules, str(base), str(n)],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for base, (name, ep, rules) in runs.items()
        ]
        for proc in procs:
            out, _ = proc.communicate(timeout=60)
            assert proc.returncode == 0, out
        got: dict[tuple[int, str], int] = {}
        for ep, sub in subs.items():
            while (item := sub.get(timeout=0.5)) is not None:
                msg = decode(item[1])
                assert isinstance(msg, JointSample | CorrectionMessage)
                base = msg.seq // 1000 * 1000
                assert runs[base][1] == ep
                got[base, item[0]] = got.get((base, item[0]), 0) + 1
    finally:
        for sub in subs.values():
            sub.close()
        for session in receivers.values():
            session.close()
    assert got == {
        (1000, "keo/demo/encoder"): n,  # the encoder's own samples; its corrections refused
        (5000, "keo/demo/encoder"): n,  # no rules on either side: everything gets through
        (5000, "keo/demo/correction"): n,
    }


def test_the_real_chain_through_a_router_with_rules_on_every_session(demo_config, tmp_path):
    """Every process as a user runs it, each under its own certificate with keo's rules:
    `keo router`, `keo run` behind it, the mocks, both `keo adapter`s. A client identity
    (the Client API and `keo status`) gets estimates, the service's status and each
    adapter's own status, which the adapters answer through the router."""
    pki = tmp_path / "pki"
    pki.mkdir()
    make_pki(pki, "keo-ca", list(ROLES))
    endpoint = f"tls/localhost:{free_port()}"
    base = loopback_config(demo_config)
    leaf = {"mode": "client", "listen": [], "connect": [endpoint]}
    cfg = {name: write_identity(base, tmp_path, pki, "keo-ca", name, **leaf) for name in ROLES}
    c = {name: ["--config", str(path)] for name, path in cfg.items()}
    with process_group(tmp_path) as procs:
        procs.start("router", ["router", "--listen", endpoint, *c["router.demo"]])
        procs.start("service", ["run", *c["svc.demo"]])
        procs.start("mock-robot", ["mock", "robot", *c["enc.demo"]])
        procs.start("mock-tracker", ["mock", "tracker", *c["trk.demo"]])
        procs.start("adapter-encoder", ["adapter", "encoder", *c["enc.demo"]])
        procs.start("adapter-tracker", ["adapter", "tracker", *c["trk.demo"]])
        estimates, measured = [], 0
        with SyncClient.from_config(cfg["hmi.demo"], connect_timeout_s=30.0) as client:
            deadline = time.monotonic() + 40.0
            for est in client.estimates(timeout=20.0):
                estimates.append(est)
                measured += est.measured is not None  # the first come before alignment
                if measured >= 20 or time.monotonic() > deadline:
                    break
        status = keo("status", *c["hmi.demo"], "--json", "--timeout", "20", timeout=60)
        logs = {name: procs.log(name) for name in ("router", "service", "adapter-encoder")}
    assert measured >= 20, (len(estimates), logs)
    assert status.returncode == 0, (status.stderr, logs)
    doc = json.loads(status.stdout)
    # the service has both streams, each from its adapter through the router
    counters = doc["counters"]
    assert counters["encoder_samples"] > 0, counters
    assert counters["tracker_samples"] > 0, counters
    assert set(doc["adapters"]) == {"encoder", "tracker"}, doc["adapters"]
    for name in ("encoder", "tracker"):
        assert doc["adapters"][name]["counters"]["published"] > 0, doc["adapters"][name]


def test_keo_router_under_a_client_certificate_exits_2(demo_config, tmp_path):
    """The leaves would refuse everything it relays: `keo router` says so and stops."""
    pki = tmp_path / "pki"
    pki.mkdir()
    make_pki(pki, "keo-ca", ["hmi.demo"])
    endpoint = f"tls/localhost:{free_port()}"
    cfg = write_identity(
        demo_config,
        tmp_path,
        pki,
        "keo-ca",
        "hmi.demo",
        mode="client",
        listen=[],
        connect=[endpoint],
    )
    result = keo("router", "--listen", endpoint, "--config", str(cfg), timeout=60)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "bus.roles" in result.stderr
    assert "'hmi.demo' has the role 'client'" in result.stderr
