"""Zenoh glue of the data tier: telemetry storage, data-buffer queries, leader sync.

The pure parts live in :mod:`scmr_mesh.data` (ODS, on-disk queue, buffer);
this module puts them on the mesh.  Keys (all under :func:`scmr_mesh.keys.data`):

==============================================  ===================  =====================================
key                                             queryable of         payload -> reply
==============================================  ===================  =====================================
``scmr/data/cloud/<node>/telemetry/<robot>``    cloud                robot's batch -> ack (stored in ODS)
``scmr/data/leader/<node>/telemetry/<robot>``   leader               robot's batch -> ack (relay queue)
``scmr/data/cloud/<node>/relay``                cloud                leader's relayed batch -> ack (ODS)
``scmr/data/<tier>/<node>/buffer``              cloud and leader     ``{"sel": selector}`` -> items
``scmr/data/cloud/<node>/sync``                 cloud                ``{"epoch", "since"}`` -> delta
``scmr/data/leader/<node>/sync``                the leader           the same, for the other candidates
==============================================  ===================  =====================================

Identity: the robot id is in the telemetry key, and a tier refuses (error
reply) a batch holding records of any other robot, so the access-control rules
(:mod:`scmr_mesh.security.acl`), which allow robot X only
``.../telemetry/X``, bind stored records to the sender's certificate.  The
relay key takes batches of any robots and is allowed to servers only.

Flow ("nothing lost"):

1. A robot's :class:`TelemetryAgent` wraps ``Robot.publish_telemetry``: each
   message gets the next per-robot seq and is appended (fsync) to the robot's
   on-disk :class:`~scmr_mesh.data.queue.TelemetryQueue` *before* anything is sent.
2. A flusher thread sends the oldest unacknowledged records, in order, as a
   query to the first alive cloud node, else to the leader, exactly like frame
   requests fail over (live view of liveliness tokens + querier matching +
   deadline).  The tier answers only after the records are durable (ODS commit
   on the cloud; fsynced relay queue on the leader); then the robot acks its
   queue.  No answer: the records stay queued and are replayed later, also
   after a robot restart (the queue is on disk).
3. The leader relays what it stored to the cloud once a cloud node is alive
   again (on ``scmr/data/cloud/<node>/relay``, ``via="leader"``), and acks its
   relay queue on the cloud's answer.
4. The ODS stores each ``(robot, seq)`` once (``INSERT OR IGNORE``); replays
   and relays are counted as duplicates, never stored twice.
5. The leader pulls the data buffer of every live cloud node every
   ``--sync-period`` seconds (delta since the last revision it saw of that
   node) and serves the same buffer queries when the cloud is gone.
6. The R2R tier (docs/R2R.md): every leader-capable node keeps a
   :class:`LeaderData`.  While another node leads it pulls the leader's buffer
   (``scmr/data/leader/<leader>/sync``) every sync period (anti-entropy), so a
   successor serves buffer reads at most one period old.  Robots keep each
   telemetry record until a *cloud* has stored it (end to end): a leader's ack
   only means "relayed", so records relayed through a leader that dies are
   sent again to the cloud later, and the ODS counts them as duplicates.
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import signal
from pathlib import Path
from typing import Callable

from scmr_mesh import cliargs as ca
from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.ods import DEFAULT_FILENAME
from scmr_mesh.errors import InputError

from scmr_mesh.mesh.data_agent import TelemetryAgent, fetch_once  # noqa: F401 - re-exported
from scmr_mesh.mesh.data_cloud import CloudData, cloud_queryable_keys  # noqa: F401 - re-exported
from scmr_mesh.mesh.data_common import (  # noqa: F401 - BATCH.. re-exported for importers
    BATCH,
    DATA_VERSION,
    MAX_BACKOFF_S,
    MAX_BATCH_BYTES,
    MAX_BATCH_RECORDS,
    MAX_PENDING_RECORDS,
    RETRY_PERIOD_S,
    IngestGate,
    buffer_key,
    check_sender,
    record_from_message,
    relay_key,
    serve_buffer,
    sync_key,
    telemetry_key,
)
from scmr_mesh.mesh.data_leader import LeaderData  # noqa: F401 - re-exported

log = logging.getLogger(__name__)

__all__ = [  # the tier's public names, wherever they live now (data_common, data_cloud, data_leader, data_agent)
    "BATCH", "DATA_VERSION", "MAX_BACKOFF_S", "MAX_BATCH_BYTES", "MAX_BATCH_RECORDS", "MAX_PENDING_RECORDS",
    "RETRY_PERIOD_S", "CloudData", "IngestGate", "LeaderData", "TelemetryAgent", "add_arguments", "attach_robot",
    "buffer_key", "check_sender", "data_tier_off", "fetch_once", "record_from_message", "relay_key", "serve_buffer",
    "service_setup", "sync_key", "telemetry_key",
]


def _run_dir_from(args) -> Path | None:
    if os.environ.get("SCMR_RUN_DIR"):
        return Path(os.environ["SCMR_RUN_DIR"])
    ready = getattr(args, "ready_file", None)
    if ready:  # the fleet layout is <run dir>/ready/<peer>.ready; else the ready file's folder
        folder = Path(ready).resolve().parent
        return folder.parent if folder.name == "ready" else folder
    return None


def add_arguments(parser, role: str) -> None:
    """Add the data-tier flags of ``role`` ("cloud", "leader" or "robot") to a peer's parser."""
    g = parser.add_argument_group("data tier")
    if role == "cloud":
        g.add_argument("--ods", type=ca.PathArg("out-file", url=True, what="an ODS file path or a postgresql:// URL"), metavar="FILE|URL",
                       help="operational data store: a SQLite file (one cloud node, or several on one "
                            "host), or a postgresql:// URL that several cloud nodes share (e.g. "
                            "postgresql://scmr@db.site:5432/scmr); default $SCMR_ODS, else "
                            "$SCMR_RUN_DIR/ods.sqlite, else RUN/ods.sqlite where RUN is the folder of "
                            "--ready-file (its parent when that folder is named 'ready'), else "
                            "runs/ods.sqlite")
        g.add_argument("--data-process", choices=("auto", "on", "off"), default="auto",
                       help="run the data tier (telemetry store, signature checks, quotas, data buffer) in "
                            "a process of its own, so the records do not share an interpreter with the "
                            "frames: on, off, or auto (default): on when this process may use at least "
                            f"{DATA_PROCESS_MIN_CORES} cores (on 2 cores the hand-off costs CPU that no "
                            "spare core pays back; docs/DEPLOY.md)")
        g.add_argument("--data-params", type=ca.PathArg("in-file", what="a JSON file of buffer entries"), metavar="FILE",
                       help="JSON object of shared entries for the data buffer (keys like "
                            "'maps/site' or 'params/speed')")
    if role == "leader":  # so one --server-arg (scmr up, scmr bench mesh) reaches cloud and leader alike
        g.add_argument("--data-process", choices=("auto", "on", "off"), default="auto",
                       help="accepted for the cloud's sake: a leader's data tier (its relay queue) always "
                            "runs in its own process")
    if role in ("leader", "robot"):
        extra = "" if role == "leader" else "with --leader-capable: "
        g.add_argument("--sync-period", type=ca.positive("seconds", hi=3600, example="1"), default=1.0, metavar="S",
                       help=extra + "seconds between pulls of the data buffer: from the clouds while leading, from "
                            "the leader otherwise (default 1)")
        g.add_argument("--relay-dir", type=ca.PathArg("out-dir"), metavar="DIR",
                       help=extra + "on-disk queue of telemetry held for the cloud while leading "
                            "(default <run dir>/relay-NODE)")
    if role in ("cloud", "leader"):
        g.add_argument("--ingest-queue", type=ca.count("records", hi=10**7, example="4096"),
                       default=MAX_PENDING_RECORDS, metavar="N",
                       help="telemetry records held until they are durable (ODS commit, relay fsync); beyond "
                            "them a batch gets a busy answer and the robot keeps it and retries (default "
                            f"{MAX_PENDING_RECORDS})")
        g.add_argument("--ingest-batch", type=ca.count("records", hi=10**5, example="256"),
                       default=MAX_BATCH_RECORDS, metavar="N",
                       help=f"largest telemetry batch taken, in records (and N KiB); larger ones are refused "
                            f"(default {MAX_BATCH_RECORDS}; robots send {BATCH})")
    if role in ("cloud", "leader"):
        from scmr_mesh.data.quota import BYTES_PER_S, RECORDS_PER_S

        g.add_argument("--telemetry-quota", type=ca.non_negative("records per second", hi=10**7, example="200"),
                       default=RECORDS_PER_S, metavar="N",
                       help="telemetry records per second each robot identity may have stored or relayed "
                            "(a burst of 30 s of it); beyond it a robot's batch gets a busy answer and the "
                            "robot keeps it, a relayed record is refused and counted; 0: no limit "
                            f"(default {RECORDS_PER_S:g})")
        g.add_argument("--telemetry-quota-bytes", type=ca.non_negative("bytes per second", hi=1 << 40, example="131072"),
                       default=BYTES_PER_S, metavar="N",
                       help="the same quota in payload bytes per second (0: no limit; default "
                            f"{BYTES_PER_S})")
    if role in ("robot", "leader"):
        g.add_argument("--telemetry-queue", type=ca.PathArg("out-dir"), metavar="DIR",
                       help="the robot's on-disk telemetry queue, kept across restarts (default "
                            "RUN/queues/ID when a run dir is known from $SCMR_RUN_DIR or --ready-file, "
                            "else OUT/telemetry-queue)")
        g.add_argument("--telemetry-max-bytes", type=ca.count("bytes", lo=1024, hi=1 << 40, example="16777216"), default=16 << 20, metavar="N",
                       help="bound of the telemetry queue; beyond it new telemetry is refused and "
                            "counted (default 16 MiB)")


def service_setup(args, tier: str) -> Callable:
    """The ``setup`` hook for :func:`~scmr_mesh.mesh.peers.run_service`: installs the data tier.

    A cloud's data tier runs in a process of its own (:mod:`scmr_mesh.mesh.data_process`),
    forked by the hook's ``prefork(node)`` before the service's workers and zenoh start, when
    :func:`data_process_wanted` (``--data-process``)."""
    if tier == "cloud" and data_process_wanted(getattr(args, "data_process", "auto")):
        return _CloudDataProcessSetup(args)

    def setup(svc) -> None:
        if data_tier_off():
            log.warning("%s %s: data tier off (SCMR_DATA_TIER=off): telemetry is not stored", tier, svc.node)
            return
        run_dir = _run_dir_from(args)
        if tier == "cloud":
            data = _cloud_data(args, svc.node, *_cloud_store(args, run_dir), run_dir, record_verifier(args))
        else:
            if not getattr(args, "sync_period", 1.0) > 0:
                raise InputError(f"--sync-period must be > 0 s, got {args.sync_period}")
            relay = getattr(args, "relay_dir", None) or (run_dir or Path("runs")) / f"relay-{svc.node}"
            data = LeaderData(svc.node, relay, sync_period_s=getattr(args, "sync_period", 1.0), gate=_gate(args),
                              quota=_quota(args))
            data.start(svc)
        for key, cb in data.queryables():
            svc.add_queryable(key, cb)
        svc.data = data
        atexit.register(data.close)

    return setup


#: ``--data-process auto`` forks the cloud's data process from this many usable cores up.  On the
#: 2-core box, 16 robots at 5 Hz: the cloud's interpreter 1.05-1.11 s per 8 s with it against
#: 1.39-1.43 s without, but 0.55-0.58 s more in the child, and no core to spare for it
#: (docs/BENCHMARKS.md "256 robots on the 16-core device").
DATA_PROCESS_MIN_CORES = 4


def data_process_wanted(choice: str) -> bool:
    """Whether a cloud runs its data tier in a process of its own (``--data-process``)."""
    from scmr_mesh._cpu import usable_cores

    if choice in ("on", "off"):
        return choice == "on"
    return usable_cores() >= DATA_PROCESS_MIN_CORES


def _cloud_store(args, run_dir: Path | None) -> tuple[str | Path, dict | None]:
    """The cloud's store target (``--ods``, ``$SCMR_ODS``, the run's, ``runs/``) and ``--data-params``."""
    from scmr_mesh.data.ods import default_db_path, store_target

    if getattr(args, "ods", None):
        path = store_target(args.ods)
    elif os.environ.get("SCMR_ODS") or run_dir is None:
        path = default_db_path()
    else:
        path = run_dir / DEFAULT_FILENAME
    params = None
    if getattr(args, "data_params", None):
        try:
            params = json.loads(Path(args.data_params).read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"--data-params {args.data_params}: not a readable JSON file ({exc})") from None
        if not isinstance(params, dict):
            raise InputError(f"--data-params {args.data_params}: must hold a JSON object, "
                             f"got {type(params).__name__}")
    return path, params


def _cloud_data(args, node: str, path, params, run_dir: Path | None, verifier) -> CloudData:
    data = CloudData(node, path, params=params, gate=_gate(args), verifier=verifier, quota=_quota(args))
    if run_dir is not None:
        data.stats_path = run_dir / f"ingest-{node}.json"
    log.info("cloud %s: operational data store %s (%s)", node, data.ods.name, data.ods.backend)
    return data


class _CloudDataProcessSetup:
    """The cloud's data tier in its own process: ``prefork(node)`` checks the flags and forks the
    child (which opens the store); the hook itself waits for the store and declares the queryables."""

    def __init__(self, args) -> None:
        self.args = args
        self.proc = None

    def prefork(self, node: str) -> None:
        from scmr_mesh.mesh.data_process import DataProcess

        if data_tier_off():
            return
        args = self.args
        run_dir = _run_dir_from(args)
        path, params = _cloud_store(args, run_dir)  # bad flags fail here, in the cloud, in one line
        verifier = record_verifier(args)
        _gate(args), _quota(args)
        # a dead data process stops the cloud (it then exits 1), so a supervisor restarts both
        self.proc = DataProcess(node, lambda: _cloud_data(args, node, path, params, run_dir, verifier),
                                on_death=lambda: os.kill(os.getpid(), signal.SIGTERM))
        self.proc.start()
        atexit.register(self.proc.close)

    def __call__(self, svc) -> None:
        from scmr_mesh.mesh.data_process import DataProcessError

        if data_tier_off():
            log.warning("cloud %s: data tier off (SCMR_DATA_TIER=off): telemetry is not stored", svc.node)
            return
        if self.proc is None:
            raise RuntimeError("the cloud's data tier was not forked: run_service calls prefork(node) first")
        try:
            self.proc.wait_ready()
        except DataProcessError as exc:
            raise StoreError(str(exc)) from None
        self.proc.attach(svc, cloud_queryable_keys(svc.node))
        svc.data = self.proc


def _gate(args) -> IngestGate:
    """The ingest bounds of ``--ingest-queue`` and ``--ingest-batch``."""
    batch = int(getattr(args, "ingest_batch", None) or MAX_BATCH_RECORDS)
    return IngestGate(max_pending=int(getattr(args, "ingest_queue", None) or MAX_PENDING_RECORDS),
                      max_batch_records=batch, max_batch_bytes=batch << 10)


def _quota(args):
    """The per-robot quota of ``--telemetry-quota`` and ``--telemetry-quota-bytes``."""
    from scmr_mesh.data.quota import BYTES_PER_S, RECORDS_PER_S, Quota

    return Quota(float(getattr(args, "telemetry_quota", RECORDS_PER_S)),
                 float(getattr(args, "telemetry_quota_bytes", BYTES_PER_S)))


def _tls_credentials(args) -> Path | None:
    """The credentials directory of the peer's mutual-TLS security profile, or None (insecure, usrpwd)."""
    if not getattr(args, "security", None):
        return None
    from scmr_mesh.security.profile import load_profile

    profile = load_profile(args.security, credentials=getattr(args, "credentials", None))
    return profile.credentials if profile.kind == "tls" else None


def record_verifier(args):
    """A cloud's :class:`~scmr_mesh.data.signing.RecordVerifier` under mutual TLS (records must be
    signed by their robot, issue #28 item 3), else None."""
    creds = _tls_credentials(args)
    if creds is None:
        return None
    from scmr_mesh.data.signing import RecordVerifier

    return RecordVerifier(creds)


def record_signer(args, identity: str):
    """The robot's :class:`~scmr_mesh.data.signing.RecordSigner` (its own TLS key) under mutual TLS, else None."""
    creds = _tls_credentials(args)
    if creds is None:
        return None
    from scmr_mesh.data.signing import RecordSigner
    from scmr_mesh.security.credentials import peer_files

    return RecordSigner(peer_files(creds, identity, need=("key",)).key)


def data_tier_off() -> bool:
    """True when ``SCMR_DATA_TIER=off``: peers run without the data tier (to measure its cost)."""
    return os.environ.get("SCMR_DATA_TIER", "").lower() in ("off", "0", "no")


def attach_robot(robot, args) -> TelemetryAgent | None:
    """Wrap ``robot``'s telemetry with a :class:`TelemetryAgent` configured from ``args``.

    Returns None (nothing wrapped) when :func:`data_tier_off`.
    """
    if data_tier_off():
        return None
    qdir = getattr(args, "telemetry_queue", None)
    if not qdir:
        run_dir = _run_dir_from(args)
        # in a run dir the queue is per robot id, so a restarted robot (new --out) keeps it
        qdir = run_dir / "queues" / robot.id if run_dir is not None else Path(args.out) / "telemetry-queue"
    return TelemetryAgent(robot, qdir, max_bytes=getattr(args, "telemetry_max_bytes", 16 << 20),
                          deadline_ms=getattr(args, "deadline_ms", 1000.0), signer=record_signer(args, robot.id))


__all__ = [
    "CloudData", "IngestGate", "LeaderData", "TelemetryAgent", "add_arguments", "attach_robot", "buffer_key",
    "check_sender", "record_from_message", "relay_key", "service_setup", "sync_key", "telemetry_key",
]
