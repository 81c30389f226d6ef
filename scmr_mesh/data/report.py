"""Telemetry accounting for fleet and scenario reports.

:func:`telemetry_report` compares what each robot says it sent (seqs
``1..sent``) with what the operational data store holds, and returns the
``{"telemetry": {...}}`` block of a report.  Pure: reads of the store (SQLite or PostgreSQL) only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.ods import OperationalDataStore, is_dsn
from scmr_mesh.data.queue import seq_ranges


def telemetry_report(
    store: OperationalDataStore | str | Path,
    sent: Mapping[str, int],
    *,
    queued: Mapping[str, int] | None = None,
    refused: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """Count telemetry per robot and in total.

    Parameters
    ----------
    store : OperationalDataStore or path
        The cloud's ODS (a path is opened read-only).
    sent : mapping robot -> int
        How many telemetry messages each robot produced (its seqs are ``1..sent``).
    queued : mapping robot -> int, optional
        Messages still in each robot's on-disk queue at the end (reported as
        ``queued``; they are not in the store yet, so they also count as lost
        until they are replayed).
    refused : mapping robot -> int, optional
        Records each robot's queue refused (full, or the file system refused
        the write); they kept their seqs, so they are already among the
        missing seqs and in ``lost`` (reported as ``refused`` per robot).

    Returns
    -------
    dict
        ``{"telemetry": {"sent", "stored", "duplicates", "lost", "conflicts",
        "per_robot": {robot: {"sent", "stored", "duplicates", "conflicts",
        "lost", "missing", "unexpected", "incarnations", "stored_earlier_incarnations"
        [, "queued"]}}}}`` where ``stored`` counts distinct ``(robot, seq)`` of the
        robot's current incarnation with ``1 <= seq <= sent``, ``lost =
        sent - stored``, ``missing`` lists the missing seqs as ranges (at most
        20), ``unexpected`` counts stored seqs beyond ``sent``, and
        ``conflicts`` counts messages refused because their ``(robot, seq)``
        was already stored with other content (a robot that started over with
        a fresh queue: those messages are lost even when ``lost`` is 0).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from scmr_mesh.data.record import make_record
    >>> with OperationalDataStore(pathlib.Path(tempfile.mkdtemp()) / "o.sqlite") as ods:
    ...     _ = ods.insert([make_record("r1", s) for s in (1, 2, 2, 4)], received_from="cloud")
    ...     t = telemetry_report(ods, {"r1": 4})["telemetry"]
    >>> t["sent"], t["stored"], t["duplicates"], t["lost"], t["per_robot"]["r1"]["missing"]
    (4, 3, 1, 1, ['3'])
    """
    own = not isinstance(store, OperationalDataStore)
    ods = OperationalDataStore(store, readonly=True) if own else store
    try:
        counts = ods.counts()
        per_robot: dict[str, dict[str, Any]] = {}
        for robot in sorted(set(sent) | set(counts)):
            n_sent = int(sent.get(robot, 0))
            seqs = ods.seqs(robot) if robot in counts else []
            in_range = [s for s in seqs if 1 <= s <= n_sent]
            have = set(in_range)
            missing = [s for s in range(1, n_sent + 1) if s not in have]
            row: dict[str, Any] = {
                "sent": n_sent,
                "stored": len(in_range),
                "duplicates": counts.get(robot, {}).get("duplicates", 0),
                "conflicts": counts.get(robot, {}).get("conflicts", 0),
                "lost": n_sent - len(in_range),
                "missing": seq_ranges(missing, limit=20),
                "unexpected": len(seqs) - len(in_range),
                # issue 25 item 10: stored and lost count the robot's current incarnation (its queue
                # folder's); records of earlier ones (a wiped queue) are counted apart, never as its seqs
                "incarnations": counts.get(robot, {}).get("incarnations", 0),
                "stored_earlier_incarnations": (counts.get(robot, {}).get("stored_all", 0)
                                                - counts.get(robot, {}).get("stored", 0)),
            }
            if queued is not None:
                row["queued"] = int(queued.get(robot, 0))
            if refused is not None:
                row["refused"] = int(refused.get(robot, 0))
            per_robot[robot] = row
    finally:
        if own:
            ods.close()
    keys = ("sent", "stored", "duplicates", "lost", "conflicts") + (("refused",) if refused is not None else ())
    total = {k: sum(r[k] for r in per_robot.values()) for k in keys}
    return {"telemetry": {**total, "per_robot": per_robot}}


def queue_sent(queue_dir: str | Path) -> tuple[int, int]:
    """``(sent, queued)`` from a robot's on-disk telemetry queue (last seq handed out, unacked)."""
    from scmr_mesh.data.queue import TelemetryQueue

    with TelemetryQueue(queue_dir, readonly=True) as q:
        st = q.stats()
    return st.next_seq - 1, st.depth


def robot_summary(robot_dir: str | Path) -> dict[str, Any] | None:
    """A robot's ``telemetry.json`` (written at exit), or None when missing or unreadable."""
    import json

    summary = Path(robot_dir) / "telemetry.json"
    try:
        d = json.loads(summary.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def robot_sent(robot_dir: str | Path) -> tuple[int, int]:
    """``(sent, queued)`` of one robot from its output folder.

    Reads ``telemetry.json`` (written at a clean exit); after a crash it opens
    the robot's on-disk queue instead (``telemetry-queue/``): ``sent`` is the
    last seq handed out, ``queued`` what is still waiting for an ack.
    Returns ``(0, 0)`` for a robot that never produced telemetry.
    """
    robot_dir = Path(robot_dir)
    d = robot_summary(robot_dir)
    if d is not None:
        try:
            return int(d["sent"]), int(d["queued"])
        except (KeyError, TypeError, ValueError):
            pass
    qdir = robot_dir / "telemetry-queue"
    if not qdir.is_dir():
        return 0, 0
    return queue_sent(qdir)


def run_telemetry(run_dir: str | Path, robots: list[str] | None = None, *,
                  ods_path: str | Path | None = None) -> dict[str, Any]:
    """The ``{"telemetry": ...}`` block of a fleet run (the fleet layout of ``scmr up``).

    Parameters
    ----------
    run_dir : path
        Holds ``ods.sqlite`` (the cloud's default there), ``queues/<id>/`` (the
        robots' telemetry queues when they run with a ready file in the run
        dir) and ``robots/<id>/``.
    robots : list of str, optional
        Robot ids (default: every folder under ``queues/``, else ``robots/``).
    ods_path : path or str, optional
        The ODS file when it is not ``run_dir/ods.sqlite``, or the
        ``postgresql://`` URL of the store the cloud nodes shared.

    Returns
    -------
    dict
        As :func:`telemetry_report`, plus ``"ods"`` (the file, or None when no
        cloud ever stored anything: then every sent message counts as lost).
    """
    run_dir = Path(run_dir)
    queues = run_dir / "queues"
    if robots is None:
        base = queues if queues.is_dir() else run_dir / "robots"
        robots = sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []
    sent, queued, refused = {}, {}, {}
    for rid in robots:
        if (queues / rid).is_dir():  # peers with a run dir keep the queue there, across restarts
            sent[rid], queued[rid] = queue_sent(queues / rid)
        else:
            sent[rid], queued[rid] = robot_sent(run_dir / "robots" / rid)
        # the robot's own count at exit: refusals, and seqs it handed out that never reached
        # its queue's files (a queue on a file system that refused every write)
        d = robot_summary(run_dir / "robots" / rid) or {}
        try:
            refused[rid] = int(d.get("refused", 0))
            sent[rid] = max(sent[rid], int(d.get("sent", 0)))
        except (TypeError, ValueError):
            refused[rid] = 0
    if is_dsn(ods_path):  # a PostgreSQL store (several cloud nodes)
        from scmr_mesh.data.ods_pg import redact

        try:
            rep = telemetry_report(ods_path, sent, queued=queued, refused=refused)
            rep["telemetry"]["ods"] = redact(ods_path)
            return rep
        except StoreError as exc:
            if "holds no operational data store" not in str(exc):
                raise
    else:
        ods = Path(ods_path) if ods_path is not None else run_dir / "ods.sqlite"
        if ods.is_file():
            rep = telemetry_report(ods, sent, queued=queued, refused=refused)
            rep["telemetry"]["ods"] = str(ods)
            return rep
    per = {r: {"sent": sent[r], "stored": 0, "duplicates": 0, "conflicts": 0, "lost": sent[r],
               "missing": seq_ranges(list(range(1, sent[r] + 1)), limit=20), "unexpected": 0, "queued": queued[r],
               "refused": refused[r]}
           for r in robots}
    tot = sum(sent.values())
    return {"telemetry": {"sent": tot, "stored": 0, "duplicates": 0, "lost": tot, "conflicts": 0,
                          "refused": sum(refused.values()), "per_robot": per, "ods": None}}


def settle_telemetry(run_dir: str | Path, robots: list[str] | None = None, *, timeout_s: float = 10.0,
                     ods_path: str | Path | None = None) -> dict[str, Any]:
    """:func:`run_telemetry`, polled until nothing more can arrive or ``timeout_s`` passes.

    Nothing more can arrive when every lost record is one a robot's queue
    refused (those never reach the store).

    Call it after the robots stopped and before the cloud and leader stop:
    the leader forwards what it relayed within a fraction of a second once a
    cloud node is up.
    """
    import time

    end = time.monotonic() + timeout_s
    while True:
        rep = run_telemetry(run_dir, robots, ods_path=ods_path)
        t = rep["telemetry"]
        # records the robots' queues refused can never arrive: do not wait for them
        if t["lost"] - t.get("refused", 0) <= 0 or time.monotonic() >= end:
            return rep
        time.sleep(0.2)


def fleet_telemetry(run_dir: str | Path, robots: list[str] | None = None, *,
                    wait: bool = True, timeout_s: float = 5.0,
                    ods: str | Path | None = None) -> dict[str, Any]:
    """The report's ``"telemetry"`` value for a fleet run; never raises, never None.

    For ``scmr up`` / scenarios: call it after the robots stopped and, with
    ``wait=True``, while the cloud still runs (it waits up to ``timeout_s``
    for relayed telemetry to land).  When the store cannot be read (a
    destroyed ODS, say), the block still counts what the robots sent, counts
    every record as lost (none can be shown stored) and says why in
    ``"error"``.
    """
    import logging

    try:
        rep = settle_telemetry(run_dir, robots, timeout_s=timeout_s if wait else 0.0, ods_path=ods)
        return rep["telemetry"]
    except Exception as exc:  # a report must not fail over telemetry accounting
        why = f"{type(exc).__name__}: {exc}"
        logging.getLogger(__name__).error("telemetry accounting for %s failed: %s", run_dir, why)
        return unreadable_telemetry(run_dir, robots, why, ods=ods)


def _redact(dsn) -> str:
    from scmr_mesh.data.ods_pg import redact

    return redact(dsn)


def unreadable_telemetry(run_dir: str | Path, robots: list[str] | None, why: str, *,
                         ods: str | Path | None = None) -> dict[str, Any]:
    """A telemetry block for a run whose store could not be read: sent as far as known, all lost."""
    run_dir = Path(run_dir)
    per: dict[str, dict[str, Any]] = {}
    for rid in robots or []:
        try:
            qdir = run_dir / "queues" / rid
            sent, queued = queue_sent(qdir) if qdir.is_dir() else robot_sent(run_dir / "robots" / rid)
        except Exception:  # the robots' own counts are unreadable too: nothing known
            sent, queued = 0, 0
        per[rid] = {"sent": sent, "stored": 0, "duplicates": 0, "conflicts": 0, "lost": sent,
                    "missing": seq_ranges(list(range(1, sent + 1)), limit=20), "unexpected": 0, "queued": queued}
    tot = sum(r["sent"] for r in per.values())
    return {"sent": tot, "stored": 0, "duplicates": 0, "lost": tot, "conflicts": 0, "per_robot": per,
            "ods": _redact(ods) if is_dsn(ods) else str(ods if ods is not None else run_dir / "ods.sqlite"),
            "error": f"the store could not be read ({why})"}


__all__ = ["fleet_telemetry", "queue_sent", "robot_sent", "robot_summary", "run_telemetry", "settle_telemetry", "telemetry_report",
           "unreadable_telemetry"]
