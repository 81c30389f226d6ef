"""Zenoh configuration for scmr peers, built in layers and validated.

Layers, later wins: scmr defaults (:data:`DEFAULTS`) -> ``--config FILE``
(JSON5, zenoh's own format) -> ``--cfg KEY:JSON5`` overrides -> explicit flags
(``--listen``, ``--connect``, ``--lease-ms``, mode).  A default only applies
where the file left zenoh's built-in value untouched.

The defaults encode the measured facts (``docs/ZENOH.md``): multicast scouting
off (peers are wired with explicit endpoints), gossip on (robots find each
other through the leader), lease 500 ms with 4 keep-alives (silent link loss
seen in ~400 ms, no false expiries), fast reconnect ``connect/retry
{50, 50, 1}`` (a dead endpoint is retried every 50 ms), shared memory off and ``transport/unicast/open_timeout`` 1000 ms (bounds
``close()``), and ``wait_before_close`` (how long a reliable send may wait for
queue space) half the lease, so a send on a silently dead link gives up
within the lease instead of zenoh's 5 s, during which the whole process stopped
sending (docs/ZENOH.md section 8).  Zenoh itself does not validate the lease: ``keep_alive`` 0
panics in Rust and lease 0 loops, so :func:`check` rejects both.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import ConfigError

log = logging.getLogger(__name__)

#: Default lease (ms) of every scmr peer; detection of a silent loss ~0.8x this.
DEFAULT_LEASE_MS = 500
#: Default keep-alives per lease (zenoh's ``keep_alive`` divisor).
DEFAULT_KEEP_ALIVE = 4

#: Zenoh key bounding the size of one message a peer reassembles from fragments;
#: a larger one is dropped by the transport before Python sees any of it.
MAX_MESSAGE_KEY = "transport/link/rx/max_message_size"
#: Default of :data:`MAX_MESSAGE_KEY`: the largest request a service admits
#: (``wire.MAX_REQUEST_BYTES``, 32 MiB) plus room for msgpack and zenoh framing.
#: Zenoh's own default is 1 GiB: one 300 MB query raised a cloud's peak RSS by
#: ~600 MB before the service could refuse it (docs/ZENOH.md section 9).
MAX_MESSAGE_BYTES = 40 << 20

#: How long a client keeps trying to reach its router when it opens (ms).
CLIENT_CONNECT_TIMEOUT_MS = 30000

#: scmr defaults: zenoh key -> JSON value.
DEFAULTS: dict[str, Any] = {
    "scouting/multicast/enabled": False,
    "scouting/gossip/enabled": True,
    "transport/link/tx/lease": DEFAULT_LEASE_MS,
    "transport/link/tx/keep_alive": DEFAULT_KEEP_ALIVE,
    "transport/unicast/open_timeout": 1000,
    # a dead endpoint is retried every 50 ms, so a restarted cloud is reached
    # before it has declared its token (docs/ZENOH.md section 3: the trade-off)
    "connect/retry": {"period_init_ms": 50, "period_max_ms": 50, "period_increase_factor": 1},
    "listen/retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2},
    # one link per pair of peers: with zenoh's "always" both ends of a gossip
    # pair dial each other and keep 2 links; when a peer's link dies silently,
    # closing each dead link ties up one of zenoh's RX threads (docs/ZENOH.md section 8)
    "scouting/gossip/autoconnect_strategy": {"peer": {"to_router": "always", "to_peer": "greater-zid"}},
    # SHM: first large query pays 17-26 ms to set it up, SIGKILLed peers leave
    # /dev/shm files, and at our sizes the median gain is nil (docs/ZENOH.md)
    "transport/shared_memory/enabled": False,
    # every peer refuses oversized messages in the transport (issue #12, docs/ZENOH.md section 9)
    MAX_MESSAGE_KEY: MAX_MESSAGE_BYTES,
    # zenoh.open() waits up to scouting/delay (500 ms) for the peers gossip announced to be
    # connected; with to_peer "greater-zid" the lower-zid side never dials, so in 9 of 24
    # measured joins open() sat the full 500 ms.  Off: open() returns in ~0.5 ms and the
    # leader's token still arrives in ~5 ms (docs/R2R.md "Discovery"); peers gate every request
    # on liveliness and querier matching, so nothing is sent before the links exist.
    "open/return_conditions/connect_scouted": False,
}

MODES = ("peer", "client", "router")

#: Zenoh key (microseconds) bounding how long a reliable ("block") send waits
#: for queue space before zenoh declares the link unresponsive and closes it.
WAIT_BEFORE_CLOSE_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"


@dataclass
class MeshConfig:
    """Everything needed to open a zenoh session for an scmr peer.

    Attributes
    ----------
    mode : str
        ``peer`` (default), ``client`` or ``router``.
    listen, connect : list of str
        Zenoh endpoints such as ``tcp/127.0.0.1:7447``.
    config_file : str or None
        A zenoh JSON5 config file applied over the defaults.
    cfg : list of str
        ``KEY:JSON5`` overrides, e.g. ``transport/link/tx/lease:1000``.
    lease_ms : int or None
        Shortcut for ``transport/link/tx/lease`` (applied last).
    keep_alive : int or None
        Shortcut for ``transport/link/tx/keep_alive``.
    security : str or None
        Security profile TOML (``peers/secure/mtls.toml``): TLS with mutual
        certificates or usrpwd, and access control (docs/SECURITY.md).
    credentials : str or None
        Overrides the profile's credentials directory (made by ``scmr certs``).
    identity : str or None
        This peer's name in the credentials (node name or robot id).
    max_message_bytes : int or None
        At least this many bytes for :data:`MAX_MESSAGE_KEY` (a service with a
        larger ``--max-request-bytes`` raises the transport's limit with it).
    """

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    config_file: str | None = None
    cfg: list[str] = field(default_factory=list)
    lease_ms: int | None = None
    keep_alive: int | None = None
    security: str | None = None
    credentials: str | None = None
    identity: str | None = None
    max_message_bytes: int | None = None

    def build(self):
        """Return a validated ``zenoh.Config``; raise :class:`ConfigError` if unusable."""
        return build_config(self)


def _parse_override(item: str) -> tuple[str, str]:
    key, sep, value = item.partition(":")
    if not sep or not key or not value:
        raise ConfigError(
            f"--cfg expects KEY:JSON5, got {item!r}; example: --cfg 'transport/link/tx/lease:1000'"
        )
    return key.strip(), value.strip()


def build_config(mc: MeshConfig):
    """Build a ``zenoh.Config`` from ``mc`` (see module docstring for the layers).

    Raises
    ------
    ConfigError
        Unreadable file, unknown key, bad JSON5, unusable lease/keep_alive.
    """
    import zenoh

    if mc.mode not in MODES:
        raise ConfigError(f"mode must be one of {MODES}, got {mc.mode!r}")
    pristine = zenoh.Config()
    if mc.config_file:
        path = Path(mc.config_file)
        if not path.is_file():
            raise ConfigError(f"zenoh config file {path} not found; pass an existing JSON5 file to --config")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ConfigError(f"zenoh config file {path} is invalid: {exc}") from None
    else:
        conf = zenoh.Config()
    for key, value in DEFAULTS.items():
        if _untouched(conf, pristine, key):
            _insert(conf, key, json.dumps(value), source="scmr defaults")
    wbc_pinned = not _untouched(conf, pristine, WAIT_BEFORE_CLOSE_KEY)
    for item in mc.cfg:
        key, value = _parse_override(item)
        _insert(conf, key, value, source="--cfg")
        wbc_pinned = wbc_pinned or key.strip("/") == WAIT_BEFORE_CLOSE_KEY
    _insert(conf, "mode", json.dumps(mc.mode), source="mode")
    if mc.mode == "client" and _untouched(conf, pristine, "connect/timeout_ms"):
        # a client tries its router once by default and fails to open; a router busy with a fleet's
        # TLS handshakes (256 robots starting together on 16 cores, load 230) refused some: retry
        # (every 50 ms, connect/retry) for up to CLIENT_CONNECT_TIMEOUT_MS (docs/ZENOH.md section 13)
        _insert(conf, "connect/timeout_ms", json.dumps(CLIENT_CONNECT_TIMEOUT_MS), source="client mode")
    if mc.listen:
        _insert(conf, "listen/endpoints", json.dumps(list(mc.listen)), source="--listen")
    if mc.connect:
        _insert(conf, "connect/endpoints", json.dumps(list(mc.connect)), source="--connect")
    if mc.lease_ms is not None:
        _insert(conf, "transport/link/tx/lease", json.dumps(int(mc.lease_ms)), source="--lease-ms")
    if mc.keep_alive is not None:
        _insert(conf, "transport/link/tx/keep_alive", json.dumps(int(mc.keep_alive)), source="keep_alive")
    if mc.max_message_bytes is not None and (_get(conf, MAX_MESSAGE_KEY) or 0) < mc.max_message_bytes:
        _insert(conf, MAX_MESSAGE_KEY, json.dumps(int(mc.max_message_bytes)), source="--max-request-bytes")
    if not wbc_pinned:
        # A send blocked on a silently dead link holds zenoh's pipeline lock: the
        # link cannot be torn down and zenoh's TX thread stalls, so every other
        # link of the process goes quiet too (docs/ZENOH.md section 8).  Frames and
        # their replies use congestion control drop (the robot's queriers), so what
        # still blocks is small (declarations, tokens): give up on a link that takes
        # none of it for half a lease, before the lease itself expires.
        lease = _get(conf, "transport/link/tx/lease")
        if isinstance(lease, int) and lease > 0:
            _insert(conf, WAIT_BEFORE_CLOSE_KEY, json.dumps(max(10, lease // 2) * 1000), source="lease")
    if mc.security:
        from scmr_mesh.mesh.security import apply_security
        from scmr_mesh.security.profile import load_profile

        if not mc.identity:
            raise ConfigError(f"--security {mc.security} needs this peer's name (--node for cloud, leader and "
                              "router, --id for robots), the name of its certificate from `scmr certs`")
        apply_security(conf, load_profile(mc.security, credentials=mc.credentials), identity=mc.identity,
                       listen=mc.listen, connect=mc.connect)
    check(conf)
    return conf


def _untouched(conf, pristine, key: str) -> bool:
    """Whether ``conf`` still holds zenoh's built-in value for ``key``."""
    try:
        return conf.get_json(key) == pristine.get_json(key)
    except Exception:
        return True


def _insert(conf, key: str, value: str, *, source: str) -> None:
    try:
        conf.insert_json5(key, value)
    except Exception as exc:
        raise ConfigError(f"{source}: cannot set zenoh key {key!r} to {value!r}: {exc}") from None


def _get(conf, key: str) -> Any:
    """The JSON value of ``key`` (zenoh's get_json returns JSON text)."""
    raw = conf.get_json(key)
    try:
        return json.loads(raw) if isinstance(raw, str) else raw
    except ValueError:
        return raw


def check(conf) -> None:
    """Reject settings zenoh accepts but cannot run with.

    Raises
    ------
    ConfigError
        ``lease`` < 10 ms (0 makes zenoh loop connect/disconnect; below 10 ms
        links flap) or ``keep_alive`` < 2 (0 panics, 1 gives spurious expiries).
    """
    lease = _get(conf, "transport/link/tx/lease")
    ka = _get(conf, "transport/link/tx/keep_alive")
    if not isinstance(lease, int) or lease < 10:
        raise ConfigError(
            f"transport/link/tx/lease must be an integer >= 10 ms, got {lease!r}; "
            f"use {DEFAULT_LEASE_MS} (0 makes zenoh reconnect in a loop)"
        )
    if not isinstance(ka, int) or ka < 2:
        raise ConfigError(
            f"transport/link/tx/keep_alive must be an integer >= 2, got {ka!r}; "
            f"use {DEFAULT_KEEP_ALIVE} (0 panics in zenoh, 1 expires idle links)"
        )
    if lease // ka < 2:
        raise ConfigError(
            f"lease {lease} ms / keep_alive {ka} leaves under 2 ms between keep-alives; "
            "raise the lease or lower keep_alive"
        )


def add_arguments(parser, *, lease_default: int | None = None) -> None:
    """Add the shared zenoh flags to an argparse parser.

    ``--listen EP``, ``--connect EP`` (repeatable), ``--config FILE``,
    ``--cfg KEY:JSON5`` (repeatable), ``--lease-ms MS``, ``--zmode``.
    """
    g = parser.add_argument_group("zenoh")
    g.add_argument("--listen", action="append", default=[], metavar="EP",
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--connect", action="append", default=[], metavar="EP",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--config", type=ca.PathArg("in-file", what="a zenoh JSON5 config file"), metavar="FILE", default=None,
                   help="zenoh JSON5 config file applied over scmr's defaults (see peers/*.json5)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:JSON5",
                   help="zenoh config override, e.g. 'scouting/multicast/enabled:true' (repeatable)")
    g.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), default=lease_default, metavar="MS",
                   help=f"link lease in ms (default {DEFAULT_LEASE_MS}); silent link loss is "
                        "detected in about 0.8 x lease")
    g.add_argument("--zmode", choices=MODES, default=None,
                   help="zenoh session mode (default: peer; router for `scmr router`)")
    g.add_argument("--security", metavar="PROFILE", default=None,
                   help="security profile TOML, e.g. peers/secure/mtls.toml (mutual TLS + access control; "
                        "tcp/ endpoints become tls/); credentials from `scmr certs` (docs/SECURITY.md)")
    g.add_argument("--credentials", type=ca.PathArg("in-dir", what="a folder written by scmr certs"), metavar="DIR", default=None,
                   help="credentials directory made by `scmr certs` (overrides the profile and $SCMR_CREDENTIALS)")
    g.add_argument("--insecure", action="store_true",
                   help="run without authentication or access control (anyone who reaches the port can join, "
                        "serve false answers and take telemetry); peers refuse to start without --security "
                        "unless this is given")


def from_args(args, *, mode: str = "peer") -> MeshConfig:
    """A :class:`MeshConfig` from parsed :func:`add_arguments` flags."""
    return MeshConfig(
        mode=getattr(args, "zmode", None) or mode,
        listen=list(args.listen or []),
        connect=list(args.connect or []),
        config_file=args.config,
        cfg=list(args.cfg or []),
        lease_ms=args.lease_ms,
        security=getattr(args, "security", None),
        credentials=getattr(args, "credentials", None),
        identity=getattr(args, "node", None) or getattr(args, "id", None),
    )


def open_session(mc: MeshConfig):
    """Open a zenoh session for ``mc``; raise :class:`MeshError` when zenoh refuses."""
    import zenoh

    from scmr_mesh.errors import MeshError

    conf = mc.build()
    lease = _get(conf, "transport/link/tx/lease")
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT)
    _zenoh_logging()
    try:
        session = zenoh.open(conf)
    except Exception as exc:
        raise MeshError(
            f"cannot open a zenoh session (listen={mc.listen}, connect={mc.connect}): {exc}; "
            "check that the listen port is free and the endpoints are well formed"
        ) from None
    # a silently dead TCP link must not hold zenoh's threads for its 10 s linger
    # (zenoh issues #1101, #2718; docs/ZENOH.md section 8)
    from scmr_mesh.mesh import tcpguard

    g = tcpguard.guard(session, lease if isinstance(lease, int) else None)
    if g is not None:
        _GUARDS[id(session)] = g
    return session


#: The TCP link guard of each open session (by ``id``), closed with it.
_GUARDS: dict[int, Any] = {}


#: zenoh's runtime threads (read once per process from ``$ZENOH_RUNTIME`` at the
#: first ``zenoh.open``).  Zenoh's defaults are 1 TX and 2 RX workers; closing a
#: silently dead link can block a worker until the kernel gives up on the
#: socket (at worst until the route comes back), and with 2 RX workers two dead
#: links stopped the peer from receiving anything (docs/ZENOH.md section 8).
ZENOH_RUNTIME_DEFAULT = "(rx: (worker_threads: 4), tx: (worker_threads: 2))"

#: Environment variable that turns on zenoh's own (Rust) log, e.g.
#: ``SCMR_ZENOH_LOG=zenoh::net::routing=debug,info``; it goes to stdout, which
#: ``scmr up`` and ``scmr scenario run`` keep in each peer's log file.
ZENOH_LOG_ENV = "SCMR_ZENOH_LOG"


def _zenoh_logging() -> None:
    """Start zenoh's Rust log when ``$SCMR_ZENOH_LOG`` asks for it (once per process)."""
    spec = os.environ.get(ZENOH_LOG_ENV, "").strip()
    if not spec:
        return
    import zenoh

    try:
        zenoh.init_log_from_env_or(spec)
    except Exception as exc:  # already initialised, or a bad filter
        log.debug("zenoh log not started (%s=%r): %s", ZENOH_LOG_ENV, spec, exc)


def close_session(session) -> None:
    """Close ``session``, never raising (close can time out on a dead endpoint)."""
    g = _GUARDS.pop(id(session), None)
    if g is not None:
        g.close()
    try:
        session.close()
    except Exception as exc:  # zenoh: "close operation timed out!"
        log.warning("zenoh session close failed: %s", exc)


def endpoints(values: Sequence[str]) -> list[str]:
    """Normalise endpoint strings (strip blanks, drop empties)."""
    return [v.strip() for v in values if v and v.strip()]
