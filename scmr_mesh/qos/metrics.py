"""QoS metrics of a fleet run, computed from request records and fault times.

Pure functions (no I/O, no processes, no middleware): ``scmr up``,
``scmr bench mesh`` and ``scmr scenario run`` all summarise runs with them.

Inputs
------
A *record* is one finished request as a robot writes it to ``records.jsonl``::

    {"robot": "r0", "seq": 3, "sent_unix_ns": ..., "received_unix_ns": ...,
     "tor_ms": 4.2, "ok": true, "tier": "cloud" | "leader" | "local" | None,
     "served_by": "cloud0", "attempts": [...], "error": None, ...}

Only ``robot``, ``ok``, ``tier``, ``sent_unix_ns``, ``received_unix_ns`` and
``tor_ms`` are read.  Missing ``tor_ms`` is derived from the two timestamps.

A *fault* is a dict describing one injected failure::

    {"kind": "crash", "target": "cloud0", "tier": "cloud",
     "start_unix_ns": ..., "end_unix_ns": ... | None,
     "robots": None | ["r0", ...], "fallback": ["leader"]}

``tier`` is the serving tier the fault takes away (``None`` for faults that
take away no tier, e.g. a leader crash is ``"leader"``); ``end_unix_ns`` is
the time the tier was restored (process restarted, link back up), ``None`` if
never; ``robots`` limits the fault to some robots (a link drop), ``None`` means
every robot; ``fallback`` lists the tiers that count as a failover answer
(default: the tiers after ``tier`` in :data:`TIERS`, without ``local``).

Definitions (issue 3)
---------------------
ToR
    ``received - sent`` of *succeeded* requests, in ms.  Failed requests have
    no time of response; they lower the RoR instead.
RoR
    ``succeeded / requests`` (``None`` for a run with no requests).
Percentiles
    Linear interpolation between closest ranks (Hyndman & Fan type 7, the
    default of ``numpy.percentile``).
Failover gap (per robot, per fault)
    From ``t0 = max(fault start, sending time of the robot's first request
    the faulted tier failed to answer)`` to the robot's first answer from a
    fallback tier.  A request "the tier failed to answer" is one that was in
    flight at the fault start or sent during the fault, and was answered
    neither by that tier nor by a tier preferred to it (a leader crash while
    the cloud serves goes unnoticed).  A robot with no such request has no gap (it did not notice
    the fault); a robot with such requests but no fallback answer has gap
    ``None``.  Per fault the report keeps the largest gap, or ``None`` if any
    affected robot never got a fallback answer.
Hedges (issue 24)
    A request is *hedged* when its record says ``"hedged": true`` (a second
    copy went to the next live tier because the first was silent past the hedge
    delay); ``hedge_won`` when that copy's answer was the one used.  The
    *duplicate* of a hedged request is the work of a node whose answer was not
    used (the hedge's node when none answered), counted on its tier.  A copy
    sent once more to the same node (``"resend": true`` on that attempt, when
    the hedge or, with no other live node, the first copy was silent; the
    request is counted in ``resent``) is no extra work: a node serves a request
    once and answers every copy.
Mismatched replies (issue 25 item 8)
    Replies a robot refused because they did not echo the robot, seq and frame
    digest of the request they came for (a replayed or wrong answer), or were
    not a trusted reply of the node asked (``bad_reply``: forged): the
    ``mismatched`` count of each attempt, summed, and by ``tier/node`` of the
    node that sent them.  Any is a lying or broken server: the run's problems.
Failback gap (per fault with an end)
    From the restore time (``end_unix_ns``) to the first answer the restored
    tier gives again (the earliest ``received`` of a request it served);
    ``None`` if it never answers again.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

__all__ = [
    "TIERS",
    "failback_gap_ms",
    "failover_gaps_ms",
    "hedge_counts",
    "mismatch_counts",
    "largest_gap",
    "percentile",
    "ror",
    "summarize",
    "tier_counts",
    "tor_summary",
    "tor_values_ms",
]

#: Serving tiers, in the order a robot prefers them.
TIERS: tuple[str, ...] = ("cloud", "leader", "peer", "local")

Record = Mapping[str, Any]
Fault = Mapping[str, Any]


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile of ``values`` by linear interpolation.

    Parameters
    ----------
    values : sequence of float, length N >= 1
        Samples, in any order.
    q : float
        Percentile in ``[0, 100]``.

    Returns
    -------
    float
        ``x[k] + (x[k+1] - x[k]) * f`` where ``x`` is sorted and
        ``(N - 1) * q / 100 = k + f`` (numpy's default method).

    Examples
    --------
    >>> percentile([1, 2, 3, 4], 50)
    2.5
    """
    if not values:
        raise ValueError("percentile of an empty sequence is undefined; got 0 values")
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"q must be within [0, 100], got {q}")
    xs = sorted(float(v) for v in values)
    pos = (len(xs) - 1) * q / 100.0
    k = math.floor(pos)
    f = pos - k
    if k + 1 >= len(xs):
        return xs[-1]
    return xs[k] + (xs[k + 1] - xs[k]) * f


def _tor_ms(rec: Record) -> float | None:
    tor = rec.get("tor_ms")
    if tor is not None:
        return float(tor)
    sent, recv = rec.get("sent_unix_ns"), rec.get("received_unix_ns")
    if sent is None or recv is None:
        return None
    return (int(recv) - int(sent)) / 1e6


def _ok(rec: Record) -> bool:
    return bool(rec.get("ok"))


def tor_values_ms(records: Iterable[Record]) -> list[float]:
    """Times of response (ms) of the succeeded requests, in record order."""
    out = []
    for r in records:
        if _ok(r):
            t = _tor_ms(r)
            if t is not None:
                out.append(t)
    return out


def tor_summary(records: Iterable[Record]) -> dict[str, float | None]:
    """``{"p50", "p90", "p99", "max", "mean"}`` of the ToR of succeeded requests (ms).

    Every value is ``None`` when no request succeeded.
    """
    vals = tor_values_ms(records)
    if not vals:
        return {"p50": None, "p90": None, "p99": None, "max": None, "mean": None}
    return {
        "p50": percentile(vals, 50),
        "p90": percentile(vals, 90),
        "p99": percentile(vals, 99),
        "max": max(vals),
        "mean": sum(vals) / len(vals),
    }


def ror(records: Iterable[Record]) -> float | None:
    """Reliability of response: succeeded / requests (``None`` if no requests)."""
    n = ok = 0
    for r in records:
        n += 1
        ok += _ok(r)
    return ok / n if n else None


def tier_counts(records: Iterable[Record]) -> dict[str, int]:
    """Succeeded requests per serving tier, plus ``"failed"``.

    Keys are always ``cloud``, ``leader``, ``peer``, ``local`` and ``failed``; a
    succeeded request with another tier name adds that key.
    """
    counts = {t: 0 for t in TIERS}
    counts["failed"] = 0
    for r in records:
        if not _ok(r):
            counts["failed"] += 1
        else:
            tier = r.get("tier") or "unknown"
            counts[tier] = counts.get(tier, 0) + 1
    return counts


def _finish_ns(rec: Record) -> int | None:
    recv = rec.get("received_unix_ns")
    if recv is not None:
        return int(recv)
    tor = rec.get("tor_ms")
    if tor is not None and rec.get("sent_unix_ns") is not None:
        return int(rec["sent_unix_ns"]) + int(float(tor) * 1e6)
    return None


def _fallback_tiers(fault: Fault) -> tuple[str, ...]:
    fb = fault.get("fallback")
    if fb is not None:
        return tuple(fb)
    tier = fault.get("tier")
    if tier not in TIERS:
        return ()
    return tuple(t for t in TIERS[TIERS.index(tier) + 1 :] if t != "local")


def _affected(rec: Record, fault: Fault) -> bool:
    robots = fault.get("robots")
    return robots is None or str(rec.get("robot")) in {str(x) for x in robots}


def failover_gaps_ms(records: Iterable[Record], fault: Fault) -> dict[str, float | None]:
    """Failover gap of each robot that noticed ``fault`` (see the module docstring).

    Parameters
    ----------
    records : iterable of record dicts
        Every robot's records of the run.
    fault : fault dict
        Needs ``tier`` and ``start_unix_ns``; ``end_unix_ns``, ``robots``
        and ``fallback`` are optional.

    Returns
    -------
    dict
        ``{robot: gap_ms or None}`` for the robots that had at least one
        request the faulted tier failed to answer; ``None`` means no fallback
        answer came.  Empty when the fault takes away no tier.
    """
    tier = fault.get("tier")
    fallback = _fallback_tiers(fault)
    if tier is None:
        return {}
    start = int(fault["start_unix_ns"])
    end = fault.get("end_unix_ns")
    end = int(end) if end is not None else None
    by_robot: dict[str, list[Record]] = {}
    for r in records:
        if not _affected(r, fault) or r.get("sent_unix_ns") is None:
            continue
        sent = int(r["sent_unix_ns"])
        if end is not None and sent >= end:
            continue  # sent after the tier came back
        if sent < start:
            fin = _finish_ns(r)
            if fin is not None and fin < start:
                continue  # finished before the fault
        if _ok(r) and r.get("tier") == tier:
            continue  # the tier answered it
        if _ok(r) and tier in TIERS and r.get("tier") in TIERS[: TIERS.index(tier)]:
            continue  # a preferred tier answered it: the faulted tier was not needed
        by_robot.setdefault(str(r.get("robot")), []).append(r)
    gaps: dict[str, float | None] = {}
    for robot, recs in by_robot.items():
        first_sent = min(int(r["sent_unix_ns"]) for r in recs)
        t0 = max(start, first_sent)
        answers = [
            int(r["received_unix_ns"])
            for r in recs
            if _ok(r) and r.get("tier") in fallback and r.get("received_unix_ns") is not None
            and int(r["received_unix_ns"]) >= t0
        ]
        gaps[robot] = (min(answers) - t0) / 1e6 if answers else None
    return gaps


def largest_gap(gaps: Mapping[str, float | None]) -> float | None:
    """The largest per-robot gap; ``None`` if any robot has none or no robot noticed."""
    if not gaps or any(g is None for g in gaps.values()):
        return None
    return max(g for g in gaps.values() if g is not None)


def failback_gap_ms(records: Iterable[Record], fault: Fault) -> float | None:
    """From the fault's ``end_unix_ns`` to the first answer of the restored tier (ms).

    ``None`` when the fault has no end, takes away no tier, or the tier never
    answered again.
    """
    tier = fault.get("tier")
    end = fault.get("end_unix_ns")
    if tier is None or end is None:
        return None
    end = int(end)
    firsts = [
        int(r["received_unix_ns"])
        for r in records
        if _ok(r) and r.get("tier") == tier and r.get("received_unix_ns") is not None
        and int(r["received_unix_ns"]) >= end and _affected(r, fault)
    ]
    return (min(firsts) - end) / 1e6 if firsts else None


def hedge_counts(records: Iterable[Record]) -> dict[str, Any]:
    """``{"hedged", "hedge_won", "hedge_rate", "resent", "duplicates_by_tier"}`` of ``records`` (module docstring).

    >>> recs = [{"hedged": True, "hedge_won": True, "attempts": [
    ...     {"tier": "cloud", "outcome": "superseded"}, {"tier": "leader", "outcome": "ok", "hedge": True}]},
    ...     {"hedged": False, "attempts": [{"tier": "cloud", "outcome": "ok"}]}]
    >>> hedge_counts(recs)
    {'hedged': 1, 'hedge_won': 1, 'hedge_rate': 0.5, 'resent': 0, 'duplicates_by_tier': {'cloud': 1}}
    >>> resent = {"hedged": True, "hedge_won": True, "attempts": [{"tier": "cloud", "outcome": "superseded"},
    ...     {"tier": "leader", "outcome": "superseded", "hedge": True},
    ...     {"tier": "leader", "outcome": "ok", "hedge": True, "resend": True}]}
    >>> hedge_counts([resent])["duplicates_by_tier"], hedge_counts([resent])["resent"]
    ({'cloud': 1}, 1)
    """
    n = hedged = won = resent = 0
    dup: dict[str, int] = {}
    for r in records:
        n += 1
        if not r.get("hedged"):
            continue
        hedged += 1
        won += bool(r.get("hedge_won"))
        atts = list(r.get("attempts") or [])
        i = next((k for k, a in enumerate(atts) if a.get("hedge")), None)
        if i is None:
            continue
        copies = [a for a in atts[i:] if a.get("hedge")]
        resent += any(a.get("resend") for a in copies)
        pair = ([atts[i - 1]] if i > 0 else []) + copies
        ok = [a for a in pair if a.get("outcome") == "ok"]
        nodes = list(dict.fromkeys((str(a.get("tier")), a.get("node")) for a in pair))
        used = (str(ok[0].get("tier")), ok[0].get("node")) if ok else nodes[0]
        for t, _node in nodes:  # a node serves a request once, however many copies it got
            if (t, _node) != used:
                dup[t] = dup.get(t, 0) + 1
    return {"hedged": hedged, "hedge_won": won, "hedge_rate": (hedged / n) if n else None, "resent": resent,
            "duplicates_by_tier": dict(sorted(dup.items()))}


def mismatch_counts(records: Iterable[Record]) -> dict[str, int]:
    """Mismatched replies of ``records`` by ``tier/node`` of the node that sent them (module docstring).

    >>> mismatch_counts([{"attempts": [{"tier": "cloud", "node": "c0", "outcome": "mismatched", "mismatched": 2},
    ...                                {"tier": "leader", "node": "L", "outcome": "ok"}]}])
    {'cloud/c0': 2}
    """
    out: dict[str, int] = {}
    for r in records:
        for a in r.get("attempts") or []:
            n = int(a.get("mismatched") or 0)
            if n:
                k = f"{a.get('tier')}/{a.get('node')}"
                out[k] = out.get(k, 0) + n
    return dict(sorted(out.items()))


def _group_summary(recs: list[Record]) -> dict[str, Any]:
    h = hedge_counts(recs)
    m = mismatch_counts(recs)
    return {
        "requests": len(recs),
        "succeeded": sum(_ok(r) for r in recs),
        "ror": ror(recs),
        "tor_ms": tor_summary(recs),
        "by_tier": tier_counts(recs),
        "hedged": h["hedged"],
        "hedge_won": h["hedge_won"],
        "mismatched": sum(m.values()),
    }


def summarize(
    records: Iterable[Record],
    faults: Sequence[Fault] = (),
    *,
    robots: int | None = None,
) -> dict[str, Any]:
    """The report core of a run: totals, ToR, tiers, per robot, per tier, gaps.

    Parameters
    ----------
    records : iterable of record dicts
    faults : sequence of fault dicts
        In any order; gaps are listed in order of fault start.
    robots : int, optional
        Number of robots in the fleet (default: distinct robots in records).

    Returns
    -------
    dict
        ``robots, requests, succeeded, ror, tor_ms{p50,p90,p99,max,mean},
        by_tier{cloud,leader,local,failed}, hedged, hedge_won, mismatched, mismatched_by_node,
        hedges{hedged,hedge_won,hedge_rate,duplicates_by_tier}, per_robot{id: {...}},
        per_tier{tier: tor_ms}, failover_gaps_ms[...], failback_gaps_ms[...],
        faults[...]`` where each fault gains ``failover_gap_ms``,
        ``failover_by_robot`` and ``failback_gap_ms``.
    """
    recs = list(records)
    by_robot: dict[str, list[Record]] = {}
    by_tier: dict[str, list[Record]] = {}
    for r in recs:
        by_robot.setdefault(str(r.get("robot")), []).append(r)
        if _ok(r):
            by_tier.setdefault(r.get("tier") or "unknown", []).append(r)
    out: dict[str, Any] = {
        "robots": robots if robots is not None else len(by_robot),
        **_group_summary(recs),
    }
    out["hedges"] = hedge_counts(recs)
    out["mismatched_by_node"] = mismatch_counts(recs)
    out["per_robot"] = {k: _group_summary(v) for k, v in sorted(by_robot.items())}
    out["per_tier"] = {k: tor_summary(v) for k, v in sorted(by_tier.items())}
    fault_out = []
    over, back = [], []
    for f in sorted(faults, key=lambda f: int(f["start_unix_ns"])):
        gaps = failover_gaps_ms(recs, f)
        fb = failback_gap_ms(recs, f)
        entry = dict(f)
        entry["failover_by_robot"] = gaps
        entry["failover_gap_ms"] = largest_gap(gaps)
        entry["failback_gap_ms"] = fb
        fault_out.append(entry)
        if f.get("tier") is not None:
            over.append(entry["failover_gap_ms"])
            if f.get("end_unix_ns") is not None:
                back.append(fb)
    out["failover_gaps_ms"] = over
    out["failback_gaps_ms"] = back
    out["faults"] = fault_out
    return out
