"""Who led the R2R tier, and how well it passed on: the report's ``leadership`` block (pure).

Inputs are what a run leaves behind: each candidate's role changes (JSON
lines written by :class:`scmr_mesh.mesh.election.Candidate`, structured as
:class:`scmr_mesh.qos.roles.RoleChange`: ``{"t_unix_ns", "node", "event": "lead" |
"step_down", "term", "why", "by", "cause"}``; only the typed fields are read, the
``cause`` text is for people),
the robots' records (``tier``, ``served_by``, ``received_unix_ns``) and the
faults the runner injected (``kind``, ``target`` / ``peer``, ``start_unix_ns``,
``end_unix_ns``).

A process that is killed writes no ``step_down``: its lead ends at the crash
fault that killed it, or at the end of its process (``ended`` below).

Output (:func:`leadership`)::

    {"changes": [{"t_s", "from", "to", "term", "gap_ms", "cause"}],
     "leaders_at_end": [...], "converged_after_heal_ms": float | None,
     "leaders_over_time": [{"t_s", "leaders": [...]}]}

``succession_ms`` is the time from the old leader's loss (its crash, the
start of the link fault that cut it off, its stop) to the new leader's claim;
``wait_ms`` is the longest a robot went unserved after the loss (from the
loss, or from its first request after it, to its first answer from a remote
tier: the new leader, a peer robot, or the old leader finishing a request).  ``gap_ms`` has a floor of one request period (a robot at 2 Hz
asks every 500 ms); ``succession_ms`` and ``wait_ms`` do not.

``cause`` is ``start`` (the first leader), ``crash`` (the old leader's
process was killed), ``link`` (the old leader was cut off by a link fault or
a partition: the lead moved on at its lease), ``heal`` (two leaders met after
a partition healed and one stepped down) or ``stop`` (the old leader stepped
down or stopped for another reason).  ``gap_ms`` is the largest per-robot gap
between the last answer of the old leader and the first answer of the new one
(None when no robot got answers from both).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from scmr_mesh.qos.roles import RoleChange, RoleEvent, Why

LINK_FAULTS = ("link_down", "partition", "bandwidth", "latency", "loss")
#: A step-down this long after a heal counts as the heal's consolidation (``cause`` heal).
HEAL_WINDOW_NS = 5_000_000_000


def read_events(folder: str | Path) -> list[dict]:
    """Every role change in ``folder/*.jsonl`` (:class:`~scmr_mesh.qos.roles.RoleChange` lines), by time.

    Lines that are not a role change (damaged, another format) are skipped.
    """
    out: list[dict] = []
    folder = Path(folder)
    if not folder.is_dir():
        return out
    for f in sorted(folder.glob("*.jsonl")):
        for line in f.read_text(errors="replace").splitlines():
            try:
                e = json.loads(line)
            except ValueError:
                continue
            change = RoleChange.from_json(e) if isinstance(e, dict) else None
            if change is not None:
                out.append(change.to_json())
    out.sort(key=lambda e: (e["t_unix_ns"], e["event"] != "step_down"))
    return out


def _fault_peers(f: Mapping[str, Any]) -> set[str]:
    names = set()
    for k in ("target", "peer"):
        if f.get(k):
            names.add(str(f[k]))
    for k in ("link",):
        if f.get(k):
            names.update(f[k])
    for g in f.get("groups") or ():
        names.update(g)
    return names


def _cut_off(f: Mapping[str, Any], node: str, other: str | None = None) -> bool:
    """Whether link fault ``f`` separates ``node`` from ``other`` (from anyone when ``other`` is None)."""
    if f.get("kind") not in ("link_down", "partition"):
        return False
    if f.get("link"):
        return node in f["link"] and (other is None or other in f["link"])
    groups = [set(g) for g in f.get("groups") or ()]
    mine = next((g for g in groups if node in g), None)
    if mine is None or len(groups) < 2:
        return False
    return other is None or (other not in mine and any(other in g for g in groups))


def _answers(records: Iterable[Mapping[str, Any]], node: str) -> dict[str, list[int]]:
    by_robot: dict[str, list[int]] = {}
    for r in records:
        if r.get("ok") and r.get("tier") == "leader" and r.get("served_by") == node and r.get("received_unix_ns"):
            by_robot.setdefault(r["robot"], []).append(int(r["received_unix_ns"]))
    for v in by_robot.values():
        v.sort()
    return by_robot


def gap_ms(records: Sequence[Mapping[str, Any]], old: str | None, new: str, t_ns: int,
           since: int | None = None) -> float | None:
    """Largest per-robot gap between the old leader's last answer before ``t_ns`` (during its lead that
    began at ``since``) and the new one's first after."""
    if old is None:
        return None
    a_old, a_new = _answers(records, old), _answers(records, new)
    gaps = []
    for robot, olds in a_old.items():
        before = [t for t in olds if t <= t_ns and (since is None or t >= since)]
        after = [t for t in a_new.get(robot, []) if t >= (before[-1] if before else t_ns)]
        if before and after:
            gaps.append((after[0] - before[-1]) / 1e6)
    return max(gaps) if gaps else None


def succession_ms(t_lost: int | None, t_new: int) -> float | None:
    """From the old leader's loss (crash, stop) to the new leader's claim (ms)."""
    return None if t_lost is None else (t_new - t_lost) / 1e6


def _r2r_answers(records: Iterable[Mapping[str, Any]], new: str) -> dict[str, list[int]]:
    """Per robot, when a remote tier answered it (any leader, a peer robot, a cloud): not alone."""
    by_robot: dict[str, list[int]] = {}
    for r in records:
        if r.get("ok") and r.get("received_unix_ns") and r.get("tier") in ("leader", "peer", "cloud"):
            by_robot.setdefault(r["robot"], []).append(int(r["received_unix_ns"]))
    for v in by_robot.values():
        v.sort()
    return by_robot


def wait_ms(records: Sequence[Mapping[str, Any]], t_lost: int | None, new: str,
            until: int | None = None) -> float | None:
    """Longest a robot went unserved after the loss: per robot, from ``max(loss, its first request sent
    after the loss)`` to its first answer from a remote tier (the new leader, a peer robot, or the old
    leader still answering a request it held); the largest over the robots the new leader answered
    before ``until`` (the next change: robots on the far side of a partition do not count)."""
    if t_lost is None:
        return None
    waits = []
    served = _answers(records, new)
    for robot, answers in _r2r_answers(records, new).items():
        first_lead = served.get(robot, [])
        if until is not None and (not first_lead or first_lead[0] > until):
            continue
        sent_after = [int(r["sent_unix_ns"]) for r in records
                      if r.get("robot") == robot and r.get("sent_unix_ns") and int(r["sent_unix_ns"]) >= t_lost]
        # a request in flight at the loss counts from the loss
        inflight = [r for r in records if r.get("robot") == robot and r.get("sent_unix_ns")
                    and int(r["sent_unix_ns"]) < t_lost <= int(r.get("received_unix_ns") or 0)]
        start = t_lost if inflight else (min(sent_after) if sent_after else None)
        after = [t for t in answers if start is not None and t >= start]
        if after:
            waits.append((after[0] - start) / 1e6)
    return max(waits) if waits else None


def leadership(events: Sequence[Mapping[str, Any]], records: Sequence[Mapping[str, Any]],
               faults: Sequence[Mapping[str, Any]], *, t0_unix_ns: int,
               ended: Mapping[str, int] | None = None, end_unix_ns: int | None = None) -> dict[str, Any]:
    """The ``leadership`` block of a report (see the module docstring).

    Parameters
    ----------
    events : sequence of dict
        Role changes of every candidate (:func:`read_events`).
    records : sequence of dict
        Every robot record of the run.
    faults : sequence of dict
        Injected faults with ``kind``, ``start_unix_ns``, ``end_unix_ns`` and
        the peers they touch (``target``/``peer``, ``link`` or ``groups``).
    t0_unix_ns : int
        Time zero of ``t_s``.
    ended : mapping, optional
        node -> when its process ended without a ``step_down`` (killed).
    end_unix_ns : int, optional
        The end of the run: changes after it (peers stepping down as they
        stop) are left out, so ``leaders_at_end`` is who led when the robots
        finished.
    """
    ended = dict(ended or {})
    crashes = [f for f in faults if f.get("kind") == "crash"]
    for f in crashes:
        for n in _fault_peers(f):
            t = f.get("start_unix_ns")
            if t is not None and (n not in ended or t < ended[n]):
                ended.setdefault(n, t)
    # the timeline: lead and step_down events, plus process ends
    timeline: list[tuple[int, str, str, Mapping[str, Any] | None]] = []
    # the run ends at end_unix_ns, or when the first candidate stops (a graceful stop comes only
    # at the end: robots finishing their run; crashes are SIGKILLs and write nothing)
    stops = [int(e["t_unix_ns"]) for e in events
             if e.get("event") == RoleEvent.STEP_DOWN and e.get("why") == Why.STOPPING]
    if stops:
        end_unix_ns = min(stops) - 1 if end_unix_ns is None else min(end_unix_ns, min(stops) - 1)

    def within(t: int) -> bool:
        return end_unix_ns is None or t <= end_unix_ns

    for e in events:
        if within(int(e["t_unix_ns"])):
            timeline.append((int(e["t_unix_ns"]), e["event"], e["node"], e))
    for n, t in ended.items():
        if within(int(t)):
            timeline.append((int(t), "ended", n, None))
    timeline.sort(key=lambda x: (x[0], {"ended": 0, "step_down": 1, "lead": 2}[x[1]]))
    leading: dict[str, int] = {}       # node -> term
    lead_since: dict[str, int] = {}    # node -> when it took the lead it holds
    last_lost: list[tuple[int, str, str]] = []  # (t, node, how) of leads that ended
    changes: list[dict[str, Any]] = []
    over_time: list[dict[str, Any]] = []
    heals = sorted(int(f["end_unix_ns"]) for f in faults
                   if f.get("kind") in ("partition", "link_down") and f.get("end_unix_ns"))

    def note(t: int) -> None:
        state, t_s = sorted(leading), round((t - t0_unix_ns) / 1e9, 3)
        if over_time and over_time[-1]["t_s"] == t_s:  # events at one instant: keep where they ended
            over_time.pop()
        if not over_time or over_time[-1]["leaders"] != state:
            over_time.append({"t_s": t_s, "leaders": state})

    def cause_of_loss(node: str, t_lost: int) -> str:
        for f in crashes:
            if node in _fault_peers(f) and f.get("start_unix_ns") is not None \
                    and abs(int(f["start_unix_ns"]) - t_lost) < 5e9 and int(f["start_unix_ns"]) <= t_lost + 1e9:
                return "crash"
        return "stop"

    def change(t: int, prev: str | None, node: str, term: int, cause: str, t_lost: int | None,
               *, heal: bool = False) -> None:
        changes.append({
            "t_s": round((t - t0_unix_ns) / 1e9, 3), "from": prev, "to": node, "term": term,
            "gap_ms": None if prev is None else _round(gap_ms(records, prev, node, t, since=lead_since.get(prev))),
            "cause": cause, "succession_ms": 0.0 if heal else _round(succession_ms(t_lost, t)),
            "wait_ms": None if heal else _round(wait_ms(records, t_lost, node)),
        })

    for t, kind, node, e in timeline:
        if kind == "lead":
            if node in leading:
                continue
            term = int(e.get("term", 0)) if e else 0
            active = [f for f in faults if f.get("start_unix_ns") is not None and f["start_unix_ns"] <= t
                      and (f.get("end_unix_ns") is None or f["end_unix_ns"] >= t)]
            prev, cause, t_lost = None, "start", None
            if last_lost:  # the lead ended (crash, stop) and passes on
                t_lost, prev, cause = last_lost.pop()
                last_lost.clear()
                if cause == "stop" and any(_cut_off(f, prev, node) for f in active):
                    cause = "link"
            elif leading:  # another leader lives: cut off (its side keeps it), or lost to this one's view
                cut = sorted(n for n in leading if any(_cut_off(f, n, node) for f in active))
                older = sorted((n for n in leading if leading[n] < term), key=lambda n: -leading[n])
                if cut:
                    prev, cause = cut[0], "link"
                    t_lost = max(int(f["start_unix_ns"]) for f in active if _cut_off(f, prev, node))
                elif older:  # a newer term with no fault between them: the old one's token was lost
                    prev, cause = older[0], "link"  # (a blink, a half-open link); loss time unknown
            change(t, prev, node, term, cause, t_lost)
            leading[node] = term
            lead_since[node] = t
        elif kind == "step_down":
            if node not in leading:
                continue
            leading.pop(node)
            by = (e or {}).get("by") if (e or {}).get("why") == Why.OUTRANKED else None
            to = by if by in leading else None
            recent_heal = any(0 <= t - h <= HEAL_WINDOW_NS for h in heals)
            if to is not None and recent_heal:
                change(t, node, to, leading[to], "heal", None, heal=True)
            elif to is None:
                last_lost.append((t, node, "stop"))
        elif kind == "ended":
            if node in leading:
                leading.pop(node)
                last_lost.append((t, node, cause_of_loss(node, t)))
        note(t)
    # robots waited: only those the new leader served before the next change
    for i, c in enumerate(changes):
        if c.get("wait_ms") is None or c["cause"] == "heal":
            continue
        t_c = t0_unix_ns + int(c["t_s"] * 1e9)
        nxt = [t0_unix_ns + int(x["t_s"] * 1e9) for x in changes[i + 1:]]
        t_lost = t_c - int((c.get("succession_ms") or 0) * 1e6)
        c["wait_ms"] = _round(wait_ms(records, t_lost, c["to"], until=min(nxt) if nxt else None))
    converged = None
    for h in heals:
        # the first moment at or after the heal with exactly one leader (none is not converged)
        state_at = None
        for p in over_time:
            if (t0_unix_ns + p["t_s"] * 1e9) <= h:
                state_at = p
        if state_at is not None and len(state_at["leaders"]) == 1:
            c = 0.0
        else:
            after = [p for p in over_time if t0_unix_ns + p["t_s"] * 1e9 > h and len(p["leaders"]) == 1]
            c = None if not after else (t0_unix_ns + after[0]["t_s"] * 1e9 - h) / 1e6
        if c is not None:
            converged = c if converged is None else max(converged, c)
    return {
        "changes": changes,
        "leaders_at_end": sorted(leading),
        # a lead that ended with nobody taking it before the end of the run
        "unfilled": [{"t_s": round((t - t0_unix_ns) / 1e9, 3), "from": n, "cause": how}
                     for t, n, how in last_lost] if not leading else [],
        "converged_after_heal_ms": _round(converged),
        "leaders_over_time": over_time,
    }


def _round(x: float | None) -> float | None:
    return None if x is None else round(float(x), 1)


__all__ = ["LINK_FAULTS", "gap_ms", "leadership", "read_events"]
