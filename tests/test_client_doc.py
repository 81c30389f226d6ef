"""docs/CLIENT.md's client code runs against a real secured cloud (issue 25, item 5).

The ```python client``` blocks of docs/CLIENT.md are extracted and run, as an outside
client with its own certificate, against `scmr cloud --security peers/secure/mtls.toml`;
the client must get a trusted reply and its telemetry record must be in the cloud's ODS.
"""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "CLIENT.md"


def client_code() -> str:
    blocks = re.findall(r"```python client\n(.*?)```", DOC.read_text(), re.S)
    assert blocks, "docs/CLIENT.md has no ```python client``` block"
    return "\n".join(blocks)


def test_the_doc_has_a_client_block_that_compiles():
    compile(client_code(), str(DOC), "exec")


#: Run after the documented client, in its process: what the docs say about refused queries
#: (the client's own key answers the same junk payload with a `malformed` error, so the
#: silence below is the access rules', not the service's).
CLAIMS = """
session = zenoh.open(conf)
for selector in ("scmr/drivable/**", "scmr/drivable/cloud/cloud0/someone_else"):
    answers = []
    for reply in session.get(selector, payload=b"x", timeout=2.0):
        if reply.ok is not None:
            answers.append(("ok", str(reply.ok.key_expr)))
        elif reply.err.payload.to_bytes() != b"Timeout":
            answers.append(("err", reply.err.payload.to_bytes()[:80]))
    assert not answers, (selector, answers)  # docs: no reply at all under the access rules
errors = [msgpack.unpackb(r.err.payload.to_bytes(), raw=False)["code"]
          for r in session.get(f"scmr/drivable/cloud/cloud0/{NAME}", payload=b"x", timeout=5.0)
          if r.ok is None and r.err.payload.to_bytes() != b"Timeout"]
assert errors == ["malformed"], errors
session.close()
"""


def _free_port() -> int:
    from scmr_mesh.ports import free_port

    return free_port()


@pytest.mark.timeout(180)
def test_the_documented_client_is_served_and_stores_telemetry(tmp_path):
    from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, synthetic_png, wait_for

    creds = tmp_path / "certs"
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    subprocess.run([sys.executable, "-m", "scmr_mesh", "certs", "--out", str(creds), "--peers", "cloud0,client1"],
                   check=True, capture_output=True, env=env)
    port = _free_port()
    ods = tmp_path / "ods.sqlite"
    ready = tmp_path / "c.ready"
    cloud = spawn_peer(["cloud", "--node", "cloud0", "--listen", f"tls/127.0.0.1:{port}", "--workers", "1",
                        "--process", STUB, "--security", str(ROOT / "peers" / "secure" / "mtls.toml"),
                        "--credentials", str(creds), "--ready-file", str(ready), "--ods", str(ods)],
                       log_path=tmp_path / "cloud.log")
    try:
        wait_for(lambda: ready.exists() or cloud.poll() is not None, timeout=90, what="cloud ready")
        assert cloud.poll() is None, (tmp_path / "cloud.log").read_text()[-1500:]
        image = tmp_path / "frame.png"
        image.write_bytes(synthetic_png(1))
        script = tmp_path / "client.py"
        script.write_text(client_code() + CLAIMS)
        run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                             env={**env, "SCMR_CLIENT_CREDS": str(creds), "SCMR_CLIENT_NAME": "client1",
                                  "SCMR_CLIENT_CONNECT": f"tls/127.0.0.1:{port}", "SCMR_CLIENT_IMAGE": str(image)})
        assert run.returncode == 0, run.stdout[-1500:] + run.stderr[-2500:]

        def stored():
            try:
                with sqlite3.connect(f"file:{ods}?mode=ro", uri=True) as con:
                    return con.execute("SELECT robot, seq FROM telemetry WHERE robot = 'client1'").fetchall()
            except sqlite3.Error:
                return []

        wait_for(lambda: stored() == [("client1", 1)], timeout=30, what="the client's record in the ODS")
    finally:
        stop_peer(cloud, timeout=10)
