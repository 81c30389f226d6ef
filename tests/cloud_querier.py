"""Test helpers shared by the tests that talk to one real cloud process over a querier."""

from __future__ import annotations

import contextlib
from pathlib import Path

from conftest import free_port

from scmr_mesh import keys, wire
from scmr_mesh.mesh.config import MeshConfig, close_session, open_session
from scmr_mesh.mesh.testing import spawn_peer, stop_peer, wait_for


@contextlib.contextmanager
def cloud_querier(tmp: Path, node: str, *args: str, requester: str = "t1", ready_timeout: float = 120,
                  lease_ms: int = 300, query_timeout: float = 30.0, env: dict | None = None,
                  stopped: str | None = None):
    """Spawn ``scmr cloud --insecure --node NODE`` on a free local port with ``args``, wait for
    its ready file, and yield ``(proc, querier)``, the querier asking it for ``requester``'s
    drivable regions (``proc.ready_file`` is the ready file).  Afterwards the session is closed
    and the cloud stopped, asserting a clean exit (``stopped``: that assertion's message)."""
    port = free_port()
    ready = tmp / f"{node}.ready"
    log = tmp / f"{node}.log"
    p = spawn_peer(["cloud", "--insecure", "--node", node, "--listen", f"tcp/127.0.0.1:{port}", *args,
                    "--ready-file", str(ready)], log_path=log, env=env)
    try:
        p.ready_file = ready
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=ready_timeout, what=f"cloud {node} ready")
        assert p.poll() is None, log.read_text()[-2000:]
        session = open_session(MeshConfig(connect=[f"tcp/127.0.0.1:{port}"], lease_ms=lease_ms))
        try:
            q = session.declare_querier(keys.drivable_request("cloud", node, requester), timeout=query_timeout)
            wait_for(lambda: q.matching_status.matching, timeout=10, what="matching queryable")
            yield p, q
        finally:
            close_session(session)
    finally:
        assert stop_peer(p) == 0, stopped


def ask(q, payload: bytes):
    """The one reply to ``payload``: ("ok", reply) or ("err", error message), both decoded."""
    replies = list(q.get(payload=payload))
    assert len(replies) == 1, f"expected exactly one reply, got {len(replies)}"
    r = replies[0]
    if r.ok is not None:
        return "ok", wire.decode(r.ok.payload.to_bytes(), kind="reply")
    return "err", wire.decode(r.err.payload.to_bytes(), kind="error")
