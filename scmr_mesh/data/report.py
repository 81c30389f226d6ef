"""Telemetry accounting for fleet and scenario reports.

:func:`telemetry_report` compares what each robot says it sent (seqs
``1..sent``) with what the operational data store holds, and returns the
``{"telemetry": {...}}`` block of a report.  Pure: reads of the store (SQLite or PostgreSQL) only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.ods import OperationalDataStore, is_dsn
from scmr_mesh.data.queue import seq_ranges


def telemetry_report(
    store: OperationalDataStore | str | Path,
    sent: Mapping[str, int],
    *,
    queued: Mapping[str, int] | None = None,
    refused: Mapping[str, int] | None = None,
    held: Mapping[str, Iterable[int]] | None = None,
    robot_lost: Mapping[str, int] | None = None,
    dropped: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """Count telemetry per robot and in total.

    Parameters
    ----------
    store : OperationalDataStore or path
        The cloud's ODS (a path is opened read-only).
    sent : mapping robot -> int
        How many telemetry messages each robot produced (its seqs are ``1..sent``).
    queued : mapping robot -> int, optional
        Messages still in each robot's on-disk queue at the end, when their
        seqs are not known (reported as ``queued``; without ``held`` they are
        not told apart from lost ones).
    held : mapping robot -> seqs, optional
        The seqs still in each robot's on-disk queue at the end.  A missing
        seq the robot still holds is ``queued`` (delivered at its next start),
        never ``lost``; ``queued`` then counts those (held and not stored).
    robot_lost : mapping robot -> int, optional
        Records each robot itself counts as lost (its ``telemetry.json``
        ``lost``: refused by its disk and not delivered from memory, found
        corrupt on its disk); reported per robot as ``lost_on_robot``.
    dropped : mapping robot -> int, optional
        Records each robot dropped because its disk refused them and its
        memory buffer was full too (among the lost); reported as ``dropped``.
    refused : mapping robot -> int, optional
        Records each robot's disk queue refused (full, or the file system
        refused the write), reported as ``refused`` per robot; each was kept
        in the robot's memory and sent from there unless its memory bound was
        hit too, so a refused record is stored or lost like any other.

    Returns
    -------
    dict
        ``{"telemetry": {"sent", "stored", "duplicates", "lost", "conflicts",
        "per_robot": {robot: {"sent", "stored", "duplicates", "conflicts",
        "lost", "missing", "unexpected", "incarnations", "stored_earlier_incarnations"
        [, "queued", "queued_seqs"]}}}}`` (and a total ``queued`` with ``held``) where
        ``stored`` counts distinct ``(robot, seq)`` of the robot's current incarnation
        with ``1 <= seq <= sent``, ``lost = sent - stored - queued``, ``missing``
        lists the lost seqs as ranges (at most 20), ``unexpected`` counts stored
        seqs beyond ``sent``, and
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
            kept = set(held.get(robot, ())) if held is not None else set()
            gone = [s for s in missing if s not in kept]
            row: dict[str, Any] = {
                "sent": n_sent,
                "stored": len(in_range),
                "duplicates": counts.get(robot, {}).get("duplicates", 0),
                "conflicts": counts.get(robot, {}).get("conflicts", 0),
                "lost": len(gone),
                "missing": seq_ranges(gone, limit=20),
                "unexpected": len(seqs) - len(in_range),
                # issue 25 item 10: stored and lost count the robot's current incarnation (its queue
                # folder's); records of earlier ones (a wiped queue) are counted apart, never as its seqs
                "incarnations": counts.get(robot, {}).get("incarnations", 0),
                "stored_earlier_incarnations": (counts.get(robot, {}).get("stored_all", 0)
                                                - counts.get(robot, {}).get("stored", 0)),
            }
            if held is not None:
                row["queued"] = len(missing) - len(gone)
                row["queued_seqs"] = seq_ranges([s for s in missing if s in kept], limit=20)
            elif queued is not None:
                row["queued"] = int(queued.get(robot, 0))
            if robot_lost is not None:
                row["lost_on_robot"] = int(robot_lost.get(robot, 0))
            if dropped is not None:
                row["dropped"] = int(dropped.get(robot, 0))
            if refused is not None:
                row["refused"] = int(refused.get(robot, 0))
            per_robot[robot] = row
    finally:
        if own:
            ods.close()
    keys = (("sent", "stored", "duplicates", "lost", "conflicts") + (("refused",) if refused is not None else ())
            + (("queued",) if held is not None else ()) + (("dropped",) if dropped is not None else ()))
    total = {k: sum(r[k] for r in per_robot.values()) for k in keys}
    return {"telemetry": {**total, "per_robot": per_robot}}


def queue_sent(queue_dir: str | Path) -> tuple[int, int]:
    """``(sent, queued)`` from a robot's on-disk telemetry queue (last seq handed out, unacked)."""
    from scmr_mesh.data.queue import TelemetryQueue

    with TelemetryQueue(queue_dir, readonly=True) as q:
        st = q.stats()
    return st.next_seq - 1, st.depth


def queue_held(queue_dir: str | Path) -> tuple[int, list[int]]:
    """``(sent, held seqs)`` of a robot's on-disk telemetry queue: last seq handed out, seqs not acknowledged."""
    from scmr_mesh.data.queue import TelemetryQueue

    with TelemetryQueue(queue_dir, readonly=True) as q:
        st = q.stats()
        return st.next_seq - 1, [s for s, _ in q.pending()]


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
    sent, held, refused, robot_lost, dropped = _robot_counts(run_dir, robots)
    kw = {"refused": refused, "held": held, "robot_lost": robot_lost, "dropped": dropped}
    if is_dsn(ods_path):  # a PostgreSQL store (several cloud nodes)
        from scmr_mesh.data.ods_pg import redact

        try:
            rep = telemetry_report(ods_path, sent, **kw)
            rep["telemetry"]["ods"] = redact(ods_path)
            return rep
        except StoreError as exc:
            if "holds no operational data store" not in str(exc):
                raise
    else:
        ods = Path(ods_path) if ods_path is not None else run_dir / "ods.sqlite"
        if ods.is_file():
            rep = telemetry_report(ods, sent, **kw)
            rep["telemetry"]["ods"] = str(ods)
            return rep
    rep = _nothing_stored(sent, held, refused, robot_lost, dropped)
    rep["ods"] = None
    return {"telemetry": rep}


def _nothing_stored(sent: Mapping[str, int], held: Mapping[str, Iterable[int]], refused: Mapping[str, int],
                    robot_lost: Mapping[str, int], dropped: Mapping[str, int]) -> dict[str, Any]:
    """The telemetry block when no store can show a record stored: what robots hold is queued, the rest lost."""
    per = {}
    for r in sent:
        kept = {s for s in held.get(r, ()) if 1 <= s <= sent[r]}
        gone = [s for s in range(1, sent[r] + 1) if s not in kept]
        per[r] = {"sent": sent[r], "stored": 0, "duplicates": 0, "conflicts": 0, "lost": len(gone),
                  "missing": seq_ranges(gone, limit=20), "unexpected": 0, "queued": len(kept),
                  "queued_seqs": seq_ranges(sorted(kept), limit=20), "refused": refused.get(r, 0),
                  "lost_on_robot": robot_lost.get(r, 0), "dropped": dropped.get(r, 0)}
    total = {k: sum(p[k] for p in per.values()) for k in ("sent", "stored", "duplicates", "lost", "conflicts",
                                                          "refused", "queued", "dropped")}
    return {**total, "per_robot": per}


def settle_telemetry(run_dir: str | Path, robots: list[str] | None = None, *, timeout_s: float = 10.0,
                     ods_path: str | Path | None = None) -> dict[str, Any]:
    """:func:`run_telemetry`, polled until nothing more can arrive or ``timeout_s`` passes.

    Nothing more can arrive when every record not stored is one its robot
    counts as lost itself (refused by its disk and not delivered from memory):
    a record a robot still holds may yet arrive through the leader it was
    relayed to.

    Call it after the robots stopped and before the cloud and leader stop:
    the leader forwards what it relayed within a fraction of a second once a
    cloud node is up.  Once the robots have stopped, only what a leader holds
    can still arrive: when every robot's summary says it handed no unstored
    record to a leader (``relayed_unstored`` 0), nothing is waited for.  (A
    restarted robot relays its backlog again from the first record when no
    cloud takes it, so what an earlier life relayed is counted there too.)
    """
    import time

    end = time.monotonic() + timeout_s
    while True:
        rep = run_telemetry(run_dir, robots, ods_path=ods_path)
        t = rep["telemetry"]
        # records the robots count as lost can never arrive: do not wait for them
        unstored = t["lost"] + t.get("queued", 0)
        gone = sum(r.get("lost_on_robot", r.get("refused", 0)) for r in t["per_robot"].values())
        if unstored - gone <= 0 or time.monotonic() >= end or not _leader_may_hold(Path(run_dir), t["per_robot"]):
            return rep
        time.sleep(0.2)


def _leader_may_hold(run_dir: Path, robots: Iterable[str]) -> bool:
    """Whether a leader may still hold records of these (stopped) robots that no store has yet.

    True unless every robot's summary (written at a clean exit) says it relayed none that is
    unstored; a robot without a readable summary (killed, say) may have relayed anything.
    """
    for rid in robots:
        d = robot_summary(run_dir / "robots" / rid)
        try:
            if d is None or int(d["relayed_unstored"]) > 0:
                return True
        except (KeyError, TypeError, ValueError):
            return True
    return False


def fleet_telemetry(run_dir: str | Path, robots: list[str] | None = None, *,
                    wait: bool = True, timeout_s: float = 5.0,
                    ods: str | Path | None = None) -> dict[str, Any]:
    """The report's ``"telemetry"`` value for a fleet run; never raises, never None.

    For ``scmr up`` / scenarios: call it after the robots stopped and, with
    ``wait=True``, while the cloud still runs (it waits up to ``timeout_s``
    for relayed telemetry to land).  When the store cannot be read (a
    destroyed ODS, say), the block still counts what the robots sent, counts what they still hold as queued and
    the rest as lost (none can be shown stored) and says why in
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


def _robot_counts(run_dir: Path, robots: Iterable[str]):
    """What each robot sent and still holds (its queue), and its own refused/lost/dropped counts at exit."""
    queues = run_dir / "queues"
    sent, held, refused, robot_lost, dropped = {}, {}, {}, {}, {}
    for rid in robots:
        qdir = queues / rid if (queues / rid).is_dir() else run_dir / "robots" / rid / "telemetry-queue"
        # peers with a run dir keep the queue there, across restarts: what it still holds is queued
        try:
            sent[rid], held[rid] = (queue_held(qdir) if qdir.is_dir()
                                    else (robot_sent(run_dir / "robots" / rid)[0], []))
        except Exception:  # the robot's own counts are unreadable too: nothing known
            sent[rid], held[rid] = 0, []
        # the robot's own count at exit: refusals, and seqs it handed out that never reached
        # its queue's files (a queue on a file system that refused every write)
        d = robot_summary(run_dir / "robots" / rid) or {}
        try:
            refused[rid] = int(d.get("refused", 0))
            robot_lost[rid] = int(d.get("lost", refused[rid]))
            dropped[rid] = int(d.get("dropped", 0))
            sent[rid] = max(sent[rid], int(d.get("sent", 0)))
        except (TypeError, ValueError):
            refused[rid] = robot_lost[rid] = dropped[rid] = 0
    return sent, held, refused, robot_lost, dropped


def unreadable_telemetry(run_dir: str | Path, robots: list[str] | None, why: str, *,
                         ods: str | Path | None = None) -> dict[str, Any]:
    """A telemetry block for a run whose store could not be read: what the robots still hold is queued, the rest lost."""
    # the same counts as run_telemetry (a queue under robots/<id>/telemetry-queue, dropped records)
    rep = _nothing_stored(*_robot_counts(Path(run_dir), robots or []))
    return {**rep, "ods": _redact(ods) if is_dsn(ods) else str(ods if ods is not None else run_dir / "ods.sqlite"),
            "error": f"the store could not be read ({why})"}


__all__ = ["fleet_telemetry", "queue_held", "queue_sent", "robot_sent", "robot_summary", "run_telemetry", "settle_telemetry", "telemetry_report",
           "unreadable_telemetry"]
