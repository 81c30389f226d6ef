"""Security profiles: how a peer authenticates and which ACL it enforces (pure).

A profile is a small TOML file (examples in ``peers/secure/``)::

    [security]
    kind = "tls"              # "tls" (mutual certificates), "usrpwd" or "none"
    credentials = "certs"     # directory made by `scmr certs` (relative to the CWD)
    acl = true                # enforce the fleet's access-control policy

:func:`zenoh_settings` turns a profile plus the peer's identity into a flat mapping
``{config key path: JSON value}`` which :mod:`scmr_mesh.mesh.security` inserts into a
``zenoh.Config``.  Endpoints ``tcp/host:port`` become ``tls/host:port`` under TLS, and
TLS peers accept only the ``tls`` protocol.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import tomllib

from scmr_mesh.errors import ConfigError
from scmr_mesh.security.acl import KeyLayout, build_acl
from scmr_mesh.security.credentials import load_fleet, peer_files

KINDS: tuple[str, ...] = ("none", "tls", "usrpwd")
#: Environment variable that overrides a profile's ``credentials`` directory.
CREDENTIALS_ENV = "SCMR_CREDENTIALS"


@dataclass(frozen=True)
class SecurityProfile:
    """How a peer joins the mesh.

    Parameters
    ----------
    kind : {"none", "tls", "usrpwd"}
        Authentication: none, mutual TLS certificates, or user/password.
    credentials : Path or None
        Directory made by ``scmr certs`` (needed unless ``kind == "none"``).
    acl : bool
        Enforce the fleet's access-control policy (:func:`~scmr_mesh.security.acl.build_acl`);
        only with ``kind == "tls"``: under usrpwd the peer that dials out never learns the
        identity of the peer it reached, so rules on that link could not name a subject.
    source : Path or None
        File the profile came from (for messages).
    """

    kind: str = "none"
    credentials: Path | None = None
    acl: bool = False
    source: Path | None = None

    def __post_init__(self) -> None:
        where = f"{self.source}: " if self.source else ""
        if self.kind not in KINDS:
            raise ConfigError(
                f"{where}field security.kind is {self.kind!r}; use one of {', '.join(KINDS)}"
            )
        if self.kind != "none" and self.credentials is None:
            raise ConfigError(
                f"{where}field security.credentials is missing; set it to a directory made by "
                "`scmr certs --out DIR --peers ...`"
            )
        if self.acl and self.kind != "tls":
            raise ConfigError(
                f"{where}field security.acl is true but kind is {self.kind!r}: access control "
                "needs both ends of every link identified, which only mutual TLS gives (usrpwd "
                "identifies only peers that dial in); set kind = \"tls\" or acl = false"
            )


def load_profile(path: str | Path, *, credentials: str | Path | None = None) -> SecurityProfile:
    """Read a security profile TOML file.

    Parameters
    ----------
    path : str or Path
        The profile (``peers/secure/mtls.toml``).
    credentials : str or Path, optional, keyword-only
        Overrides the profile's credentials directory (else ``$SCMR_CREDENTIALS``, else the file).

    Raises
    ------
    ConfigError
        Missing file, bad TOML, unknown or ill-typed field (names file, field and fix).
    """
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"security profile {p} not found; see peers/secure/ for examples") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{p}: not a valid TOML security profile ({exc})") from exc
    sec = data.get("security")
    if not isinstance(sec, dict):
        raise ConfigError(f"{p}: table [security] is missing; add [security] with kind = \"tls\"")
    unknown = set(sec) - {"kind", "credentials", "acl"}
    extra = set(data) - {"security"}
    if unknown or extra:
        bad = sorted([f"security.{k}" for k in unknown] + sorted(extra))
        raise ConfigError(f"{p}: unknown field(s) {', '.join(bad)}; allowed: security.kind, "
                          "security.credentials, security.acl")
    kind = sec.get("kind", "none")
    acl = sec.get("acl", False)
    if not isinstance(kind, str):
        raise ConfigError(f"{p}: field security.kind must be a string, got {kind!r}")
    if not isinstance(acl, bool):
        raise ConfigError(f"{p}: field security.acl must be true or false, got {acl!r}")
    cred = credentials or os.environ.get(CREDENTIALS_ENV) or sec.get("credentials")
    if cred is not None and not isinstance(cred, (str, Path)):
        raise ConfigError(f"{p}: field security.credentials must be a path string, got {cred!r}")
    return SecurityProfile(kind=kind, credentials=Path(cred) if cred else None, acl=acl, source=p)


def secure_endpoint(endpoint: str, kind: str) -> str:
    """``tcp/h:p`` -> ``tls/h:p`` under TLS; other kinds leave endpoints unchanged."""
    if kind == "tls" and endpoint.startswith("tcp/"):
        return "tls/" + endpoint[len("tcp/"):]
    return endpoint


def zenoh_settings(
    profile: SecurityProfile,
    identity: str,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    layout: KeyLayout = KeyLayout(),
) -> dict[str, Any]:
    """Zenoh config entries that make ``identity`` join the mesh as ``profile`` says.

    Parameters
    ----------
    profile : SecurityProfile
    identity : str
        The peer's name in the credentials directory (certificate CN, usrpwd user).
    listen, connect : sequence of str, keyword-only
        The peer's endpoints; rewritten to ``tls/`` under TLS.
    layout : KeyLayout, keyword-only
        Keys for the ACL.

    Returns
    -------
    dict
        ``{"transport/link/tls/root_ca_certificate": "...", ...}``: key paths for
        ``zenoh.Config.insert_json5`` and JSON-serialisable values.  Empty for ``kind == "none"``.

    Raises
    ------
    ConfigError
        Missing credentials for ``identity``.
    """
    out: dict[str, Any] = {}
    if profile.kind == "none":
        return out
    assert profile.credentials is not None
    try:
        fleet = load_fleet(profile.credentials)
        fleet.get(identity)  # raises if the identity has no credentials
    except ConfigError as exc:
        where = f"{profile.source}: field security.credentials" if profile.source else "credentials"
        raise ConfigError(f"{where} ({profile.credentials}, or --credentials / ${CREDENTIALS_ENV}): {exc}") from None
    if profile.kind == "tls":
        f = peer_files(profile.credentials, identity)
        tls = "transport/link/tls"
        out.update(
            {
                f"{tls}/root_ca_certificate": str(f.ca.resolve()),
                f"{tls}/listen_certificate": str(f.cert.resolve()),
                f"{tls}/listen_private_key": str(f.key.resolve()),
                f"{tls}/connect_certificate": str(f.cert.resolve()),
                f"{tls}/connect_private_key": str(f.key.resolve()),
                f"{tls}/enable_mtls": True,
                f"{tls}/verify_name_on_connect": True,
                "transport/link/protocols": ["tls"],
            }
        )
    else:  # usrpwd
        f = peer_files(profile.credentials, identity, need=("password_file", "dictionary"))
        out["transport/auth/usrpwd"] = {
            "user": identity,
            "password": f.password(),
            "dictionary_file": str(f.dictionary.resolve()),
        }
    if listen:
        out["listen/endpoints"] = [secure_endpoint(e, profile.kind) for e in listen]
    if connect:
        out["connect/endpoints"] = [secure_endpoint(e, profile.kind) for e in connect]
    if profile.acl:
        out["access_control"] = build_acl(fleet, kind=profile.kind, layout=layout)  # type: ignore[arg-type]
    return out


def describe(settings: Mapping[str, Any]) -> dict[str, Any]:
    """``settings`` with secrets masked, for logs and ``--show``."""
    masked = dict(settings)
    if "transport/auth/usrpwd" in masked:
        masked["transport/auth/usrpwd"] = {**masked["transport/auth/usrpwd"], "password": "***"}
    return masked
