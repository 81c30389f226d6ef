"""Credentials, ACL rules and security profiles (mostly pure; zenoh only parses configs).

About 3 s (openssl makes a few EC keys).
"""

from __future__ import annotations

import json
import stat
import subprocess

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from scmr_mesh.cli import main as scmr
from scmr_mesh.errors import ConfigError, InputError
from scmr_mesh.mesh.security import apply_security, secure_config
from scmr_mesh.security.acl import ALL_MESSAGES, build_acl
from scmr_mesh.security.credentials import (
    Fleet,
    Peer,
    create_credentials,
    infer_role,
    load_fleet,
    parse_peers,
    peer_files,
)
from scmr_mesh.security.profile import (
    SecurityProfile,
    load_profile,
    secure_endpoint,
    zenoh_settings,
)


@pytest.fixture(scope="module")
def creds(tmp_path_factory):
    d = tmp_path_factory.mktemp("c") / "certs"
    create_credentials(d, "cloud,leader,robot1,robot2,edge=cloud")
    return d


def test_certificates_chain_to_the_ca_and_name_the_peer(creds):
    for name in ("cloud", "robot1", "edge"):
        f = peer_files(creds, name)
        out = subprocess.run(["openssl", "verify", "-CAfile", str(f.ca), str(f.cert)],
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        text = subprocess.run(["openssl", "x509", "-in", str(f.cert), "-noout", "-subject", "-ext",
                               "subjectAltName,extendedKeyUsage"], capture_output=True, text=True).stdout
        assert f"CN = {name}" in text and "IP Address:127.0.0.1" in text
        assert "TLS Web Server Authentication" in text and "TLS Web Client Authentication" in text
        for secret in (f.key, f.password_file, f.dictionary):
            assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert stat.S_IMODE((creds / "ca.key").stat().st_mode) == 0o600


def test_fleet_roles_and_usrpwd_dictionaries(creds):
    fleet = load_fleet(creds)
    assert fleet.servers == ["cloud", "leader", "edge"] and fleet.robots == ["robot1", "robot2"]
    users = lambda n: {line.split(":")[0] for line in (creds / n / "usrpwd.txt").read_text().splitlines()}  # noqa: E731
    assert users("cloud") == {"cloud", "leader", "robot1", "robot2", "edge"}
    # a robot accepts links from servers only and holds no other robot's password
    assert users("robot1") == {"cloud", "leader", "edge", "robot1"}
    pw = {n: (creds / n / "password").read_text().strip() for n in fleet.names()}
    assert len(set(pw.values())) == len(pw)


def test_existing_directory_is_not_overwritten(creds):
    with pytest.raises(ConfigError, match="not empty.*--force"):
        create_credentials(creds, "cloud")


@pytest.mark.parametrize("spec,match", [
    ("", "empty"), ("cloud,cloud", "twice"), ("bad name", "not allowed"), ("x=admin", "role 'admin'"),
    ("robot/1", "not allowed"),
])
def test_bad_peer_lists_are_named(spec, match):
    with pytest.raises(InputError, match=match):
        parse_peers(spec)


@given(st.text(max_size=12))
def test_role_inference_is_total(name):
    assert infer_role(name) in ("cloud", "leader", "robot", "router")


def test_lead_grants_and_priority_caps_are_kept_in_fleet_json(tmp_path):
    d = tmp_path / "c"
    create_credentials(d, "cloud,leader,r1=robot+leader-capable,r2,router0", priority={"r2": 7})
    fleet = load_fleet(d)
    assert fleet.leaders == ["leader", "r1"] and fleet.trusted == ["cloud", "router0"]
    assert fleet.priority_cap("r2") == 7 and fleet.priority_cap("r1") == 0 and fleet.priority_cap("nobody") == 0
    assert fleet.priority_cap("cloud") is None
    assert fleet.may_serve("cloud", "cloud") and not fleet.may_serve("cloud", "r1")
    assert fleet.may_serve("leader", "r1") and fleet.may_serve("peer", "leader") and not fleet.may_serve("peer", "r2")
    assert not fleet.may_serve("leader", "stranger")
    with pytest.raises(InputError, match="only a robot takes"):
        parse_peers("c=cloud+leader-capable")
    with pytest.raises(InputError, match="not in --peers"):
        parse_peers("r1", priority={"r9": 3})


def test_version_1_fleet_files_still_load(tmp_path):
    (tmp_path / "fleet.json").write_text('{"version": 1, "peers": [{"name": "c", "role": "cloud"}, '
                                         '{"name": "L", "role": "leader"}, {"name": "r", "role": "robot"}]}')
    fleet = load_fleet(tmp_path)
    assert fleet.leaders == ["L"] and fleet.priority_cap("r") is None


def test_fleet_file_errors_name_file_and_fix(tmp_path):
    with pytest.raises(ConfigError, match="fleet.json not found.*scmr certs"):
        load_fleet(tmp_path)
    (tmp_path / "fleet.json").write_text('{"version": 1, "peers": [{"name": "a"}]}')
    with pytest.raises(ConfigError, match=r"peers\[0\].*role"):
        load_fleet(tmp_path)
    (tmp_path / "fleet.json").write_text("{nope")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_fleet(tmp_path)


def _who_may(acl, subject_name, flow, message, key):
    """Evaluate our ACL for one (subject, flow, message, key) like zenoh does: allow-list, and a
    rule applies when its key expression includes the message's (a wildcard query is not let
    through by a rule that merely intersects it, docs/SECURITY.md fact 8)."""
    subjects = {s["id"] for s in acl["subjects"]
                if subject_name in s.get("cert_common_names", []) + s.get("usernames", [])}
    rules = {r["id"]: r for r in acl["rules"]}
    for pol in acl["policies"]:
        if not subjects & set(pol["subjects"]):
            continue
        for rid in pol["rules"]:
            r = rules[rid]
            if flow in r["flows"] and message in r["messages"] and any(
                    zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"]):
                return True
    return acl["default_permission"] == "allow"


def _sent(acl, sender, receiver, message, key):
    """A message passes only when the sender's egress (subject = receiver) and the receiver's
    ingress (subject = sender) allow it: every node enforces the same rules."""
    return _who_may(acl, receiver, "egress", message, key) and _who_may(acl, sender, "ingress", message, key)


FLEET = Fleet((Peer("cloud", "cloud"), Peer("leader", "leader", leader_capable=True), Peer("r1", "robot"),
               Peer("r2", "robot"), Peer("r3", "robot", leader_capable=True), Peer("router0", "router")))


def test_acl_policy_table():
    acl = build_acl(FLEET, kind="tls")
    assert acl["default_permission"] == "deny"
    sent = lambda *a: _sent(acl, *a)  # noqa: E731
    # cloud and router: trusted with everything
    assert sent("cloud", "r1", "declare_queryable", "scmr/drivable/cloud/cloud/*")
    assert sent("router0", "cloud", "query", "scmr/drivable/cloud/cloud/r1")
    # frame requests: only on the sender's own key, to any tier; replies only to that key
    assert sent("r1", "cloud", "query", "scmr/drivable/cloud/cloud/r1")
    assert sent("cloud", "r1", "reply", "scmr/drivable/cloud/cloud/r1")
    assert not sent("r1", "cloud", "query", "scmr/drivable/cloud/cloud/r2")
    assert not sent("r1", "cloud", "query", "scmr/drivable/cloud/cloud/*")
    assert not sent("r1", "cloud", "query", "scmr/drivable/**")
    assert sent("r1", "leader", "query", "scmr/drivable/leader/leader/r1")
    assert sent("r1", "r3", "query", "scmr/drivable/peer/r3/r1")
    assert not sent("r1", "r2", "query", "scmr/drivable/peer/r2/r1")  # r2 is no peer server
    # serving: a robot certificate is no cloud, no leader, no peer server unless leader-capable
    for tier in ("cloud", "leader", "peer"):
        assert not sent("r1", "r2", "declare_queryable", f"scmr/drivable/{tier}/r1/*")
        assert not sent("r1", "r2", "reply", f"scmr/drivable/{tier}/r1/r2")
        assert not sent("r1", "r2", "liveliness_token", f"scmr/alive/{tier}/r1")
    assert not sent("r3", "r1", "declare_queryable", "scmr/drivable/cloud/r3/*")
    assert not sent("r3", "r1", "liveliness_token", "scmr/alive/cloud/r3")
    assert not sent("leader", "r1", "liveliness_token", "scmr/alive/cloud/leader")
    # leader-capable identities serve the leader and peer tiers, under their own name only
    for who in ("r3", "leader"):
        for tier in ("leader", "peer"):
            assert sent(who, "r1", "declare_queryable", f"scmr/drivable/{tier}/{who}/*")
            assert sent(who, "r1", "reply", f"scmr/drivable/{tier}/{who}/r1")
            assert sent(who, "r1", "liveliness_token", f"scmr/alive/{tier}/{who}")
            assert sent(who, "r1", "put", f"scmr/load/{tier}/{who}")
        assert sent(who, "r1", "liveliness_token", f"scmr/alive/candidate/{who}")
        assert sent(who, "r1", "put", f"scmr/r2r/candidate/{who}")
        assert sent(who, "cloud", "query", "scmr/data/cloud/cloud/relay")
        assert sent(who, "cloud", "query", "scmr/data/cloud/cloud/sync")
    assert not sent("r3", "r1", "declare_queryable", "scmr/drivable/leader/leader/*")
    assert not sent("r3", "r1", "liveliness_token", "scmr/alive/leader/leader")
    # candidacy bound to the publisher; a plain robot cannot run for the lead
    assert not sent("r3", "r1", "put", "scmr/r2r/candidate/leader")
    assert not sent("r1", "r3", "put", "scmr/r2r/candidate/r1")
    assert not sent("r1", "r3", "liveliness_token", "scmr/alive/candidate/r1")
    assert not sent("r1", "r3", "declare_queryable", "scmr/r2r/candidate/r1")
    assert sent("r3", "leader", "query", "scmr/r2r/candidate/*")  # a candidate's catch-up
    assert sent("leader", "r3", "reply", "scmr/r2r/candidate/leader")
    assert not sent("r1", "r3", "reply", "scmr/r2r/candidate/r1")
    # standby candidates pull the leader's data; plain robots do not
    assert sent("r3", "leader", "query", "scmr/data/leader/leader/sync")
    assert sent("leader", "r3", "reply", "scmr/data/leader/leader/sync")
    assert not sent("r1", "leader", "query", "scmr/data/leader/leader/sync")
    assert not sent("r1", "cloud", "query", "scmr/data/cloud/cloud/sync")
    assert not sent("r1", "cloud", "query", "scmr/data/cloud/cloud/relay")
    # telemetry: own publications, own batches; buffers readable; nobody reads others' telemetry
    assert sent("r1", "cloud", "put", "scmr/telemetry/r1")
    assert not sent("r1", "cloud", "put", "scmr/telemetry/r2")
    assert sent("r1", "cloud", "query", "scmr/data/cloud/cloud/telemetry/r1")
    assert sent("r1", "r3", "query", "scmr/data/leader/r3/telemetry/r1")
    assert not sent("r1", "cloud", "query", "scmr/data/cloud/cloud/telemetry/r2")
    assert not sent("r1", "cloud", "query", "scmr/data/cloud/cloud/telemetry/*")
    assert sent("r1", "cloud", "query", "scmr/data/cloud/cloud/buffer")
    assert not sent("r1", "cloud", "declare_subscriber", "scmr/telemetry/r2")
    assert not sent("r1", "r2", "declare_subscriber", "scmr/telemetry/*")
    assert sent("r1", "cloud", "declare_subscriber", "scmr/load/**")
    # liveliness: everyone watches; tokens only under one's own name
    assert sent("r1", "cloud", "liveliness_token", "scmr/alive/robot/r1")
    assert not sent("r1", "cloud", "liveliness_token", "scmr/alive/robot/r2")
    assert sent("r1", "r2", "declare_liveliness_subscriber", "scmr/alive/**")
    # strangers: nothing
    assert not _who_may(acl, "stranger", "ingress", "query", "scmr/drivable/cloud/cloud/stranger")
    assert not _who_may(acl, "stranger", "egress", "liveliness_token", "scmr/alive/cloud/cloud")
    # only known message kinds
    assert {m for r in acl["rules"] for m in r["messages"]} <= set(ALL_MESSAGES)


def test_zenoh_accepts_the_generated_config(creds):
    prof = SecurityProfile(kind="tls", credentials=creds, acl=True)
    conf = secure_config(prof, identity="robot1", listen=["tcp/127.0.0.1:0"])
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/127.0.0.1:0"]
    assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
    with zenoh.open(conf) as s:  # zenoh validates the ACL when opening
        assert s.info.zid() is not None


def test_default_listen_becomes_tls(creds):
    conf = zenoh.Config()
    apply_security(conf, SecurityProfile(kind="tls", credentials=creds), identity="cloud")
    assert json.loads(conf.get_json("listen/endpoints"))["peer"] == ["tls/[::]:0"]


def test_usrpwd_settings_and_masking(creds):
    s = zenoh_settings(SecurityProfile(kind="usrpwd", credentials=creds), "robot1",
                       connect=["tcp/127.0.0.1:7447"])
    assert s["transport/auth/usrpwd"]["user"] == "robot1"
    assert s["connect/endpoints"] == ["tcp/127.0.0.1:7447"]
    assert "access_control" not in s


@pytest.mark.parametrize("text,match", [
    ("[security]\nkind = 'ssh'\ncredentials = 'c'\n", "security.kind is 'ssh'"),
    ("[security]\nkind = 'tls'\n", "security.credentials is missing"),
    ("[security]\nkind = 'usrpwd'\ncredentials = 'c'\nacl = true\n", "only mutual TLS"),
    ("[security]\nkind = 'tls'\ncredentials = 'c'\nacl = 'yes'\n", "security.acl must be true or false"),
    ("[security]\nkind = 'tls'\ncredentials = 'c'\ncolour = 1\n", "unknown field.*security.colour"),
    ("kind = 'tls'\n", r"table \[security\] is missing"),
    ("[security\n", "not a valid TOML"),
])
def test_bad_profiles_name_file_field_and_fix(tmp_path, text, match, monkeypatch):
    monkeypatch.delenv("SCMR_CREDENTIALS", raising=False)
    p = tmp_path / "p.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_profile(p)
    assert str(p) in str(info.value)


def test_shipped_profiles_load(repo_root, monkeypatch):
    monkeypatch.delenv("SCMR_CREDENTIALS", raising=False)
    kinds = {p.stem: load_profile(p).kind for p in sorted((repo_root / "peers" / "secure").glob("*.toml"))}
    assert kinds == {"mtls": "tls", "mtls-noacl": "tls", "usrpwd": "usrpwd"}


def test_unknown_identity_is_named(creds):
    with pytest.raises(ConfigError, match="no credentials for peer 'robot9'.*scmr certs"):
        zenoh_settings(SecurityProfile(kind="tls", credentials=creds, acl=True), "robot9")


def test_secure_endpoint():
    assert secure_endpoint("tcp/1.2.3.4:5", "tls") == "tls/1.2.3.4:5"
    assert secure_endpoint("tcp/1.2.3.4:5", "usrpwd") == "tcp/1.2.3.4:5"
    assert secure_endpoint("udp/1.2.3.4:5", "tls") == "udp/1.2.3.4:5"


def test_certs_command(tmp_path, capsys):
    assert scmr(["certs", "--out", str(tmp_path / "c"), "--peers", "cloud,robot1",
                 "--acl-json", str(tmp_path / "acl.json")]) == 0
    assert "robot1\trobot" in capsys.readouterr().out
    assert scmr(["certs", "--out", str(tmp_path / "e"), "--peers", "cloud,r1=robot+leader-capable,r2",
                 "--priority-cap", "r2=5"]) == 0
    out = capsys.readouterr().out
    assert "r1\trobot" in out and "leader-capable" in out and "priority<=5" in out
    assert json.loads((tmp_path / "acl.json").read_text())["default_permission"] == "deny"
    assert scmr(["certs", "--out", str(tmp_path / "c"), "--peers", "cloud"]) == 1
    assert "not empty" in capsys.readouterr().err
    assert scmr(["certs", "--out", str(tmp_path / "d"), "--peers", "cloud", "--days", "0"]) == 1
    assert capsys.readouterr().err.startswith("scmr: error: --days 0: out of range")


def test_bench_tls_smoke():
    from scmr_mesh.bench.tls import bench_link_latency

    res = bench_link_latency(payload_bytes=1000, queries=5, warmup=1, kinds=("none", "tls+acl"))
    assert [r["kind"] for r in res["runs"]] == ["none", "tls+acl"]
    assert all(r["p50_ms"] > 0 for r in res["runs"])


@pytest.mark.parametrize("argv", [
    ["cloud", "--node", "c"], ["leader", "--node", "L"], ["router"],
    ["robot", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r1"],
])
def test_a_peer_refuses_to_start_without_a_security_profile(argv, tmp_path, capsys):
    assert scmr([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith(f"scmr: error: scmr {argv[0]} will not join an unauthenticated mesh")
    assert "scmr certs" in err and "--insecure" in err


def test_security_and_insecure_together_are_refused(capsys, repo_root):
    assert scmr(["cloud", "--node", "c", "--insecure", "--security", str(repo_root / "peers/secure/mtls.toml")]) == 1
    assert "either --security PROFILE or --insecure, not both" in capsys.readouterr().err


def test_a_peer_whose_identity_may_not_do_its_job_is_refused_at_start(tmp_path, capsys, repo_root):
    d = tmp_path / "c"
    create_credentials(d, "cloud,r1,r2=robot+leader-capable")
    sec = ["--security", str(repo_root / "peers/secure/mtls.toml"), "--credentials", str(d)]
    assert scmr(["cloud", "--node", "r1", *sec]) == 1
    assert "identity 'r1' has role 'robot'" in capsys.readouterr().err
    assert scmr(["robot", "--id", "r1", "--leader-capable", "--synthetic", "stub", "--out", str(tmp_path / "r"),
                 *sec]) == 1
    assert "'r1' is not leader-capable" in capsys.readouterr().err
    assert scmr(["leader", "--node", "r1", *sec]) == 1
    assert "'r1' is not leader-capable" in capsys.readouterr().err
