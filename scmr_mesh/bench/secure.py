"""Credentials for the peers a bench starts (secured by default, like ``scmr up``).

:func:`bench_security` makes ``RUN/certs`` for the named identities and returns what each
peer's command line gets (``--security ... --credentials ...``) and the
:class:`~scmr_mesh.mesh.config.MeshConfig` of the bench's own in-process sessions; with
``insecure`` every peer gets ``--insecure`` and the sessions no security.
"""

from __future__ import annotations

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
