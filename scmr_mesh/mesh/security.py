"""Apply a security profile to a ``zenoh.Config`` (TLS with mutual certificates, usrpwd, ACL).

The decisions are made by the pure :mod:`scmr_mesh.security.profile`; this module only
inserts its entries into a Zenoh config, which is where ``import zenoh`` is allowed.

Example
-------
>>> import zenoh
>>> from scmr_mesh.security.profile import load_profile
>>> conf = zenoh.Config()
>>> apply_security(conf, load_profile("peers/secure/mtls.toml"), identity="robot1",
...                listen=["tcp/127.0.0.1:7450"])  # doctest: +SKIP
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Sequence

import zenoh

from scmr_mesh.errors import ConfigError
from scmr_mesh.security.profile import (
    SecurityProfile,
    describe,
    load_profile,
    zenoh_settings,
)

log = logging.getLogger(__name__)


def apply_security(
    conf: "zenoh.Config",
    profile: SecurityProfile | str | Path | None,
    *,
    identity: str,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
) -> "zenoh.Config":
    """Insert ``profile``'s authentication and access control into ``conf``.

    Parameters
    ----------
    conf : zenoh.Config
        Config built by the caller (mode, scouting, lease ...); modified in place.
    profile : SecurityProfile, path, or None
        The profile, or a TOML file to load; ``None`` leaves ``conf`` unchanged.
    identity : str, keyword-only
        This peer's name in the credentials directory.
    listen, connect : sequence of str, keyword-only
        Endpoints; pass them here (not separately) so they are turned into ``tls/``
        endpoints under TLS.  Empty means "leave what ``conf`` has".

    Returns
    -------
    zenoh.Config
        ``conf``.

    Raises
    ------
    ConfigError
        Bad profile, missing credentials, or a key Zenoh rejects.
    """
    if profile is None:
        return conf
    if not isinstance(profile, SecurityProfile):
        profile = load_profile(profile)
    settings = zenoh_settings(profile, identity, listen=listen, connect=connect)
    if profile.kind == "tls":
        # endpoints the caller did not pass (zenoh's default listen tcp/[::]:0, a config
        # file's) must become tls/ too: a TLS-only peer refuses to open tcp/ links
        for key, given in (("listen/endpoints", listen), ("connect/endpoints", connect)):
            if not given:
                current = json.loads(conf.get_json(key))
                settings[key] = _rewrite(current)
    for key, value in settings.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh.ZError
            raise ConfigError(
                f"zenoh rejected security setting {key} from "
                f"{profile.source or 'the profile'}: {exc}"
            ) from exc
    log.info("security %s for %s: %s", profile.kind, identity, sorted(describe(settings)))
    return conf


def _rewrite(value):
    """tcp/ -> tls/ in an endpoint list or a per-mode ``{mode: [endpoints]}`` map."""
    from scmr_mesh.security.profile import secure_endpoint

    if isinstance(value, list):
        return [secure_endpoint(e, "tls") for e in value]
    if isinstance(value, dict):
        return {k: _rewrite(v) for k, v in value.items()}
    return value


def secure_config(
    profile: SecurityProfile | str | Path | None,
    *,
    identity: str,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    lease_ms: int = 1000,
    mode: str = "peer",
) -> "zenoh.Config":
    """A fresh peer config for tests and tools: multicast off, gossip on, short lease, secured.

    Parameters
    ----------
    profile : SecurityProfile, path or None
    identity : str, keyword-only
    listen, connect : sequence of str, keyword-only
        ``tcp/127.0.0.1:<port>`` endpoints (become ``tls/`` under TLS).
    lease_ms : int, keyword-only
        ``transport/link/tx/lease``.
    mode : str, keyword-only
        Zenoh mode.
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tx/lease", str(int(lease_ms)))
    conf.insert_json5("transport/unicast/open_timeout", "1000")
    conf.insert_json5("connect/retry", '{"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}')
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return apply_security(conf, profile, identity=identity, listen=listen, connect=connect)


