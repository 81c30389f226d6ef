"""Credentials made for one run: what `scmr up`, `scmr demo`, `scmr scenario run` and the
benches that start peers use by default (pure: no Zenoh).

:func:`run_credentials` writes a development CA, one certificate per peer and
``fleet.json`` into ``RUN/certs`` (:func:`~scmr_mesh.security.credentials.create_credentials`),
plus ``RUN/certs/mtls.toml``, a security profile (mutual TLS and the fleet's access rules)
that names that directory by its absolute path.  :meth:`RunCredentials.args` is what each
peer's command line gets; :data:`INSECURE` is what it gets under ``--insecure``.

Example
-------
>>> from scmr_mesh.security.credentials import Peer
>>> rc = run_credentials("/tmp/run", [Peer("cloud0", "cloud"), Peer("r1", "robot")])  # doctest: +SKIP
>>> rc.args()  # doctest: +SKIP
['--security', '/tmp/run/certs/mtls.toml', '--credentials', '/tmp/run/certs']
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from scmr_mesh.security.credentials import Fleet, Peer, create_credentials

#: The flag a launcher hands every peer when the run is insecure on purpose.
INSECURE: tuple[str, ...] = ("--insecure",)
#: Folder of a run's credentials, relative to the run directory.
CERTS_DIR = "certs"
#: Profile file written into the credentials folder.
PROFILE_NAME = "mtls.toml"

PROFILE_TEXT = """\
# Written by scmr for this run: mutual TLS with the certificates beside this file and the
# fleet's access-control rules (docs/SECURITY.md).
[security]
kind = "tls"
credentials = "{credentials}"
acl = {acl}
"""


@dataclass(frozen=True)
class RunCredentials:
    """The credentials of one run: directory, profile file and fleet."""

    directory: Path
    profile: Path
    fleet: Fleet

    def args(self) -> list[str]:
        """``--security PROFILE --credentials DIR`` for a peer's command line."""
        return ["--security", str(self.profile), "--credentials", str(self.directory)]


def run_credentials(run_dir: str | Path, peers: Sequence[Peer], *, hosts: Sequence[str] = (),
                    acl: bool = True, days: int = 7) -> RunCredentials:
    """Create ``RUN/certs`` for ``peers`` (overwriting an older one) and its profile.

    Parameters
    ----------
    run_dir : path
        The run directory.
    peers : sequence of Peer
        Every identity of the run (node names, roles, lead grants, priority caps).
    hosts : sequence of str, keyword-only
        Addresses besides loopback that peers listen on (network namespaces): every
        certificate names them, so links found by gossip pass name verification.
    acl : bool, keyword-only
        Enforce the fleet's access rules (else mutual TLS only).
    days : int, keyword-only
        Certificate validity (a run's certificates are not meant to outlive it).
    """
    d = Path(run_dir).resolve() / CERTS_DIR
    fleet = create_credentials(d, list(peers), days=days, hosts=list(hosts), force=True)
    profile = d / PROFILE_NAME
    profile.write_text(PROFILE_TEXT.format(credentials=str(d).replace("\\", "\\\\").replace('"', '\\"'),
                                           acl="true" if acl else "false"))
    return RunCredentials(d, profile, fleet)


__all__ = ["INSECURE", "RunCredentials", "run_credentials"]
