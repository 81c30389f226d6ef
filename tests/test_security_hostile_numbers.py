"""Issue #28, probe 1, with real peers: a leader-capable identity (a valid certificate)
declares its leader token and publishes its candidacy with ``clock_hz: inf`` (and
NaN, an inf load, a NaN battery, terms 2^64 - 1 and 1e300).  Before, every robot exited 2
(``OverflowError`` in the live view's ranking) about 0.26 s later; now the candidacy is
refused at decode, counted and logged, and every peer keeps running and serving.
Run with ``pytest -m security``."""

from __future__ import annotations

import math
import time

import msgpack
import pytest
from test_security_default import _r2r_fleet, _session

from scmr_mesh import keys, wire
from scmr_mesh.mesh.testing import read_records, stop_peer, wait_for
from scmr_mesh.security.credentials import create_credentials

pytestmark = pytest.mark.security


def test_an_infinite_clock_candidacy_crashes_no_peer(tmp_path, repo_root):
    creds = tmp_path / "certs"
    create_credentials(creds, "leader0=leader,r1=robot+leader-capable,r3,r9=robot+leader-capable")
    profile = str(repo_root / "peers" / "secure" / "mtls.toml")
    procs, ports = _r2r_fleet(tmp_path, creds, profile)
    s = None
    try:
        wait_for(lambda: sum(r["ok"] for r in read_records(tmp_path / "r3" / "records.jsonl")) >= 3,
                 timeout=60, what="r3 served")
        s = _session(creds, profile, "r9", f"tcp/127.0.0.1:{ports['leader0']}")
        tokens = [s.liveliness().declare_token(keys.alive(role, "r9")) for role in ("candidate", "leader")]
        pub = s.declare_publisher(keys.candidate("r9"))
        hostile = [wire.make_candidate("r9", term=1, leading=True, clock_hz=1e9, power_w=1.0, battery=1.0,
                                       load=0.0) | over
                   for over in ({"clock_hz": math.inf}, {"clock_hz": math.nan}, {"load": math.inf},
                                {"term": 2**64 - 1}, {"term": 1e300}, {"battery": math.nan},
                                {"term": wire.MAX_TERM})]  # decodes; refused by the term window
        t_forge = time.time_ns()

        def attack_then_served() -> bool:
            """One round of hostile candidacies per poll, until r3 has been served 5 times since the first."""
            for msg in hostile:
                pub.put(msgpack.packb(msg, use_bin_type=True))
            return sum(r["ok"] and r["sent_unix_ns"] > t_forge
                       for r in read_records(tmp_path / "r3" / "records.jsonl")) >= 5

        wait_for(attack_then_served, timeout=30, what="r3 served while the hostile candidacies go on")
        for token in tokens:
            token.undeclare()
        dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
        assert not dead, {n: (tmp_path / f"{n}.log").read_text()[-2000:] for n in dead}
    finally:
        if s is not None:
            s.close()
        for p in procs.values():
            stop_peer(p, timeout=10)
    logs = "".join((tmp_path / f"{n}.log").read_text() for n in procs)
    assert "dropped a candidate message" in logs
    # a leader at MAX_TERM (within the schema) is beyond the term window: leader0 never yields to it
    # (before: outranked, it stepped down, and the next honest claim, MAX_TERM + 1, was refused by all)
    assert "with a term more than" in logs
    events = read_records(tmp_path / "leadership" / "leader0.jsonl")
    assert [e["cause"] for e in events if e["t_unix_ns"] > t_forge and e["event"] == "step_down"] in ([], ["stopping"]), events
    assert "OverflowError" not in logs and "internal error" not in logs
