"""A credentialed robot cannot store telemetry as another robot (docs/SECURITY.md, gap 1 closed).

Real processes: ``scmr cloud`` with the shipped mutual-TLS profile and its real data tier
(ODS on disk), and an attacker holding robot2's valid certificate (this file run as a
script).  The attacker sends telemetry batches made of *robot1's* records on every key
that could take them:

===  ==========================================  ===========================================
 #   key                                         expected with ACL
===  ==========================================  ===========================================
 1   ``scmr/data/cloud/cloud/telemetry``          no reply (the pre-fix key: no longer served)
 2   ``scmr/data/cloud/cloud/telemetry/robot1``   no reply (ACL: robot2 may query only its key)
 3   ``scmr/data/cloud/cloud/telemetry/robot2``   error reply from the service (records' robot)
 4   ``scmr/data/cloud/cloud/telemetry/*``        refused (ACL or the service: no robot named)
 5   ``scmr/data/cloud/cloud/relay``              no reply (ACL: servers only)
===  ==========================================  ===========================================

Attack ``k`` uses robot1's seq ``k``, so the ODS tells which attack landed.  A last,
honest batch of robot2's own record (seq 1) must be stored: the attacker was connected
and served.  The same run with the ACL off (``mtls-noacl.toml``) is the control: the
service check still refuses 3 and 4, while 2 and 5 reach the service (without ACL there is
no identity to check against) and are refused only by the records' signatures (robot2 signs
robot1's records with its own key), so the ACL assertions can fail.  Before the fix, attack 1
stored robot1's record with the ACL on.

About 10 s (two cloud starts).  Run alone with ``pytest -m security``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import free_port  # noqa: E402

pytestmark = pytest.mark.security

HERE = Path(__file__).resolve()

ATTACKS = [
    "scmr/data/cloud/cloud/telemetry",
    "scmr/data/cloud/cloud/telemetry/robot1",
    "scmr/data/cloud/cloud/telemetry/robot2",
    "scmr/data/cloud/cloud/telemetry/*",
    "scmr/data/cloud/cloud/relay",
]
OWN = "scmr/data/cloud/cloud/telemetry/robot2"


def attacker(argv: list[str]) -> int:
    """robot2's process: spoofed batches, then its own; prints one JSON line per query."""
    import argparse

    import msgpack
    import zenoh

    import dataclasses

    from scmr_mesh.data.record import encode_records, make_record
    from scmr_mesh.data.signing import RecordSigner
    from scmr_mesh.mesh.security import secure_config
    from scmr_mesh.security.profile import load_profile

    ap = argparse.ArgumentParser()
    ap.add_argument("--profile", required=True)
    ap.add_argument("--connect", required=True)
    a = ap.parse_args(argv)

    def show(reply) -> str:
        r = reply.ok if reply.ok is not None else reply.err
        try:
            body = msgpack.unpackb(r.payload.to_bytes(), raw=False)
        except Exception:
            body = r.payload.to_bytes().decode("utf-8", "replace")
        return json.dumps({"ok" if reply.ok is not None else "err": body})

    profile = load_profile(a.profile)
    signer = RecordSigner(profile.credentials / "robot2" / "key.pem")  # the attacker's own key

    def signed(r):
        return dataclasses.replace(r, sig=signer.sign(r.digest()))

    conf = secure_config(profile, identity="robot2", connect=[a.connect], lease_ms=1000)
    with zenoh.open(conf) as s:
        own = s.declare_querier(OWN, timeout=2.0)
        end = time.monotonic() + 20
        while not own.matching_status.matching and time.monotonic() < end:
            time.sleep(0.05)
        print(json.dumps({"ev": "matching", "own": own.matching_status.matching,
                          "peers": len(list(s.info.peers_zid()))}), flush=True)
        for k, key in enumerate(ATTACKS, start=1):
            payload = encode_records([signed(make_record("robot1", k, battery=0.1))],
                                     via="leader" if key.endswith("/relay") else None)
            replies = [show(r) for r in s.get(key, payload=payload, timeout=2.0)]
            print(json.dumps({"ev": "attack", "k": k, "key": key, "replies": replies}), flush=True)
        replies = [show(r) for r in own.get(payload=encode_records([signed(make_record("robot2", 1, battery=0.9))]))]
        print(json.dumps({"ev": "own", "replies": replies}), flush=True)
    return 0


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "attacker":
    sys.exit(attacker(sys.argv[2:]))


def _run(creds: Path, profile: Path, tmp: Path) -> tuple[list[dict], dict[str, list[int]]]:
    """One cloud + the attacker; returns the attacker's events and the ODS's seqs per robot."""
    from scmr_mesh.data.ods import OperationalDataStore
    from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, wait_for

    tmp.mkdir(parents=True, exist_ok=True)
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = {"SCMR_CREDENTIALS": str(creds)}
    ods = tmp / "ods.sqlite"
    cloud = spawn_peer(["cloud", "--node", "cloud", "--listen", ep, "--workers", "1", "--process", STUB,
                        "--security", str(profile), "--ready-file", str(tmp / "c.ready"), "--ods", str(ods)],
                       log_path=tmp / "c.log", env=env)
    att = None
    try:
        wait_for(lambda: (tmp / "c.ready").exists() or cloud.poll() is not None, timeout=60, what="cloud")
        assert cloud.poll() is None, (tmp / "c.log").read_text()[-1500:]
        penv = dict(os.environ, SCMR_CREDENTIALS=str(creds))
        penv.pop("RUST_LOG", None)
        att = subprocess.Popen([sys.executable, str(HERE), "attacker", "--profile", str(profile),
                                "--connect", ep], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               text=True, start_new_session=True, env=penv)
        try:
            out, _ = att.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(att.pid, signal.SIGKILL)
            out, _ = att.communicate()
    finally:
        if att is not None and att.poll() is None:
            os.killpg(att.pid, signal.SIGKILL)
            att.wait()
        stop_peer(cloud, timeout=5)
    events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    seqs: dict[str, list[int]] = {}
    if ods.exists():
        with OperationalDataStore(ods, readonly=True) as store:
            seqs = {r: store.seqs(r) for r in store.counts()}
    return events, seqs


@pytest.fixture(scope="module")
def credentials(tmp_path_factory):
    from scmr_mesh.security.credentials import create_credentials

    d = tmp_path_factory.mktemp("idcreds")
    create_credentials(d / "fleet", "cloud,leader,robot1,robot2")
    return d / "fleet"


def _attacks(events: list[dict]) -> dict[int, list[dict]]:
    return {e["k"]: [json.loads(r) for r in e["replies"]] for e in events if e["ev"] == "attack"}


def _own(events: list[dict]) -> list[dict]:
    return [json.loads(r) for e in events if e["ev"] == "own" for r in e["replies"]]


def test_robot_cannot_store_telemetry_as_another_robot(credentials, repo_root, tmp_path):
    events, seqs = _run(credentials, repo_root / "peers" / "secure" / "mtls.toml", tmp_path / "acl")
    assert [e["own"] for e in events if e["ev"] == "matching"] == [True], events
    # the attacker is a connected, served robot: its own record is stored
    own = _own(events)
    assert len(own) == 1 and own[0]["ok"]["stored"] == 1, events
    assert seqs.get("robot2") == [1]
    # ... and nothing it sent as robot1 landed, whatever the key
    assert "robot1" not in seqs, f"spoofed telemetry stored for robot1 (seqs = attack numbers): {seqs}"
    att = _attacks(events)
    assert att[1] == [] and att[2] == [] and att[5] == []  # not served / dropped by the ACL
    assert len(att[3]) == 1 and "robot1" in att[3][0]["err"]["error"] and "robot2" in att[3][0]["err"]["error"]
    assert all("err" in r for r in att[4])


def test_without_acl_the_service_still_checks_the_key(credentials, repo_root, tmp_path):
    """Control: no ACL.  The service refuses records that do not match the key's robot; a robot
    using another robot's key (or the relay key) reaches the service (the ACL's job), whose
    signature check (issue #28) still refuses robot1's records signed with robot2's key."""
    events, seqs = _run(credentials, repo_root / "peers" / "secure" / "mtls-noacl.toml", tmp_path / "noacl")
    assert _own(events) and _own(events)[0]["ok"]["stored"] == 1, events
    att = _attacks(events)
    assert att[1] == []  # the pre-fix key is no longer served
    err = att[3][0]["err"]["error"]
    assert "robot1" in err and "scmr/data/cloud/cloud/telemetry/robot2" in err
    assert len(att[4]) == 1 and "err" in att[4][0]
    # without ACL the robot1 key (attack 2) and the relay (attack 5) reach the service (with the ACL:
    # no reply), and only the signature check refuses them (before issue #28 both landed)
    for k in (2, 5):
        assert len(att[k]) == 1 and att[k][0]["ok"]["refused"] == 1 and att[k][0]["ok"]["stored"] == 0, att[k]
        assert "not robot1's" in att[k][0]["ok"]["refusals"][0][2]
    assert "robot1" not in seqs
