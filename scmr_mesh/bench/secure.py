"""Credentials for the peers a bench starts (secured by default, like ``scmr up``).

:func:`bench_security` makes ``RUN/certs`` for the named identities and returns what each
peer's command line gets (``--security ... --credentials ...``) and the
:class:`~scmr_mesh.mesh.config.MeshConfig` of the bench's own in-process sessions; with
``insecure`` every peer gets ``--insecure`` and the sessions no security.
:func:`bench_cloud` starts one such ``scmr cloud`` and a robot's querier on it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from scmr_mesh.mesh.config import MeshConfig
from scmr_mesh.security.credentials import Peer, parse_peers
from scmr_mesh.security.runcreds import INSECURE, RunCredentials, run_credentials


@dataclass
class BenchSecurity:
    """What a bench hands its peers (``args``) and uses for its own sessions (:meth:`mesh`)."""

    creds: RunCredentials | None
    args: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        return "insecure" if self.creds is None else "mtls+acl"

    def mesh(self, identity: str, **kw) -> MeshConfig:
        """A MeshConfig for an in-process session of ``identity`` (secured unless insecure)."""
        if self.creds is None:
            return MeshConfig(**kw)
        return MeshConfig(security=str(self.creds.profile), credentials=str(self.creds.directory),
                          identity=identity, **kw)


def bench_security(run_dir: str | Path, peers: str | Sequence[Peer], *, insecure: bool = False,
                   priority: dict[str, int] | None = None) -> BenchSecurity:
    """Credentials for ``peers`` (``"c1,L=leader,r1=robot+leader-capable"`` or Peer objects) in RUN/certs."""
    if insecure:
        return BenchSecurity(None, list(INSECURE))
    plist = parse_peers(peers, priority=priority) if isinstance(peers, str) else list(peers)
    rc = run_credentials(run_dir, plist)
    return BenchSecurity(rc, rc.args())


__all__ = ["BenchSecurity", "bench_security"]


@contextmanager
def bench_cloud(run_dir: str | Path, node: str, client: str, *, port: int, args: Sequence[str] = (),
                env: dict | None = None, insecure: bool = False, what: str = "bench") -> Iterator[tuple]:
    """One ``scmr cloud`` ``node`` (secured as deployed, its store in ``RUN/ods.sqlite``, its log in
    ``RUN/cloud.log``) and a session of robot ``client`` holding a querier on the cloud's drivable
    key, matched: yields ``(process, session, querier)``; the session is closed and the cloud stopped after.
    ``args``: more ``scmr cloud`` flags (``--workers``, ``--process``); ``what`` names the run in errors.
    """
    from scmr_mesh import keys
    from scmr_mesh.errors import MeshError
    from scmr_mesh.mesh.config import close_session, open_session
    from scmr_mesh.mesh.testing import spawn_peer, stop_peer, wait_for

    run_dir = Path(run_dir)
    ready = run_dir / "cloud.ready"
    sec = bench_security(run_dir, f"{node}=cloud,{client}=robot", insecure=insecure)
    proc = spawn_peer(["cloud", *sec.args, "--node", node, "--listen", f"tcp/127.0.0.1:{port}", *args,
                       "--ods", str(run_dir / "ods.sqlite"), "--ready-file", str(ready)],
                      log_path=run_dir / "cloud.log", env=env)
    try:
        wait_for(lambda: ready.exists() or proc.poll() is not None, timeout=120, what=f"{what} cloud ready")
        if proc.poll() is not None:
            raise MeshError(f"the {what} run's cloud exited; see {run_dir / 'cloud.log'}")
        session = open_session(sec.mesh(client, connect=[f"tcp/127.0.0.1:{port}"]))
        try:
            q = session.declare_querier(keys.drivable_request("cloud", node, client), timeout=10.0)
            wait_for(lambda: q.matching_status.matching, timeout=10, what=f"the {what} cloud's queryable")
            yield proc, session, q
        finally:
            close_session(session)
    finally:
        stop_peer(proc)
