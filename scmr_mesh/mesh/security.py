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

from scmr_mesh.errors import ConfigError, MeshError
from scmr_mesh.security.profile import SecurityProfile, describe, load_profile, zenoh_settings

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


def bench_link_latency(
    *,
    payload_bytes: int = 200_000,
    queries: int = 300,
    warmup: int = 30,
    kinds: tuple[str, ...] = ("none", "usrpwd", "tls", "tls+acl"),
    progress=None,
) -> dict:
    """Query round trip over loopback with each security kind (``scmr bench tls``).

    Two sessions in one process (a queryable replying 100 B, a querier sending
    ``payload_bytes``), shared memory off so every byte crosses the link (and TLS).

    Returns
    -------
    dict
        ``{"payload_bytes", "queries", "runs": [{"kind", "p50_ms", "p99_ms", "mean_ms"}]}``.
    """
    import socket
    import statistics
    import tempfile
    import time

    from scmr_mesh.security.credentials import create_credentials

    say = progress or (lambda m: None)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        creds = create_credentials(Path(tmp) / "certs", "cloud,robot1").directory
        for kind in kinds:
            base = kind.split("+")[0]
            prof = None if base == "none" else SecurityProfile(kind=base, credentials=creds, acl=kind.endswith("+acl"))
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            ep = f"tcp/127.0.0.1:{port}"
            confs = []
            for ident, listen, connect in (("cloud", [ep], []), ("robot1", [], [ep])):
                c = secure_config(prof, identity=ident, listen=listen, connect=connect)
                c.insert_json5("transport/shared_memory/enabled", "false")
                if not listen:
                    c.insert_json5("listen/endpoints", "[]")
                confs.append(c)
            key = "scmr/drivable/cloud/cloud"
            with zenoh.open(confs[0]) as a, zenoh.open(confs[1]) as b:
                qa = a.declare_queryable(key, lambda q: q.reply(q.key_expr, b"x" * 100), complete=True)
                q = b.declare_querier(key, timeout=5.0)
                t_end = time.monotonic() + 10
                while not q.matching_status.matching and time.monotonic() < t_end:
                    time.sleep(0.01)
                payload = b"\x00" * payload_bytes
                times = []
                for i in range(warmup + queries):
                    t0 = time.perf_counter()
                    ok = any(r.ok is not None for r in q.get(payload=payload))
                    dt = (time.perf_counter() - t0) * 1e3
                    if not ok:
                        raise MeshError(f"bench_link_latency: query over {kind} got no reply")
                    if i >= warmup:
                        times.append(dt)
                qa.undeclare()
            times.sort()
            run = {"kind": kind, "p50_ms": round(statistics.median(times), 3),
                   "p99_ms": round(times[min(len(times) - 1, int(0.99 * (len(times) - 1)))], 3),
                   "mean_ms": round(statistics.fmean(times), 3)}
            say(f"{kind}: p50 {run['p50_ms']} ms, p99 {run['p99_ms']} ms")
            runs.append(run)
    return {"payload_bytes": payload_bytes, "queries": queries, "shared_memory": False, "runs": runs}
