"""Scenario reports: JSON, Markdown and two PNG plots (OpenCV), from a run's records.

:func:`build_report` is pure (records and fault times in, a dict out): the
summary comes from :func:`scmr_mesh.qos.metrics.summarize` (the same definitions
as ``scmr up``), expectations are checked against it, energy per robot comes
from the energy model, and the thesis's Table 4.2 is put beside our figures.
:func:`write_report` writes ``report.json``, ``report.md``, ``tor.png`` and
``tiers.png``.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from scmr_mesh.scenario.plots import TIER_COLOURS, plot_tiers, plot_tor, request_rows
from scmr_mesh.scenario.spec import Scenario

__all__ = ["TIER_COLOURS", "build_report", "check_expectations", "energy_per_robot", "energy_report", "markdown", "run_problems",
           "run_report", "thesis_table", "validate_report", "write_report", "plot_tor", "plot_tiers"]

log = logging.getLogger(__name__)

REQUEST_FIELDS = ("robot", "seq", "image", "bytes_up", "bytes_down", "sent_unix_ns", "received_unix_ns",
                  "tor_ms", "ok", "tier", "served_by", "attempts", "error")


def _metric_values(summary: Mapping[str, Any], telemetry: Mapping[str, Any] | None = None) -> dict[str, float | None]:
    over: list[float] = []
    over_missing = False
    for f in summary.get("faults", []):
        by_robot = f.get("failover_by_robot") or {}
        if not by_robot:
            continue  # no robot noticed this fault
        if any(v is None for v in by_robot.values()):
            over_missing = True
        over += [v for v in by_robot.values() if v is not None]
    back = [f.get("failback_gap_ms") for f in summary.get("faults", [])
            if f.get("tier") is not None and f.get("end_unix_ns") is not None]
    tor = summary.get("tor_ms") or {}
    tiers = summary.get("by_tier") or {}
    return {
        "ror": summary.get("ror"),
        "requests": summary.get("requests"),
        "succeeded": summary.get("succeeded"),
        "tor_p50_ms": tor.get("p50"),
        "tor_p99_ms": tor.get("p99"),
        "max_failover_gap_ms": None if over_missing else (max(over) if over else 0.0),
        "max_failback_gap_ms": None if any(b is None for b in back) else (max(back) if back else 0.0),
        "leader_answers": tiers.get("leader", 0),
        "cloud_answers": tiers.get("cloud", 0),
        # not counted (None) fails its expectation: a loss that cannot be ruled out is not "0 lost"
        "telemetry_lost": None if telemetry is None or telemetry.get("lost") is None else telemetry["lost"],
        "peer_answers": tiers.get("peer", 0),
        "local_answers": tiers.get("local", 0),
        # hedged requests (issue 24): how many, and their share of the requests
        "hedged": (summary.get("hedges") or {}).get("hedged", 0),
        "hedge_rate": (summary.get("hedges") or {}).get("hedge_rate"),
        **_leadership_values(summary.get("leadership")),
        **(summary.get("multihop") or {}),
    }


def _leadership_values(lead: Mapping[str, Any] | None) -> dict[str, Any]:
    """Expectation metrics of the R2R tier (None when the run has no leadership block)."""
    if lead is None:
        return {}
    moves = [c for c in lead["changes"] if c["from"] is not None]
    succ = [c.get("succession_ms") for c in moves if c["cause"] in ("crash", "link", "stop")]
    waits = [c.get("wait_ms") for c in moves if c.get("wait_ms") is not None]
    unfilled = bool(lead.get("unfilled"))  # a lead lost and never taken: no succession at all
    return {
        "leader_changes": len(moves),
        "leaders_at_end": len(lead["leaders_at_end"]),
        "max_succession_ms": None if unfilled or any(s is None for s in succ) else (max(succ) if succ else 0.0),
        "max_leader_wait_ms": max(waits) if waits else 0.0,
        "converged_after_heal_ms": lead.get("converged_after_heal_ms"),
    }


def check_expectations(scenario: Scenario, summary: Mapping[str, Any],
                       telemetry: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
    """``[{"name", "metric", "observed", "held"}]`` for each expectation of ``scenario``.

    Checks :attr:`Scenario.checked_expectations`: the declared ones plus the
    default ``telemetry_lost <= 0``.  A metric that could not be measured
    (e.g. a failover that never happened, telemetry not counted) is ``None``
    and fails its expectation.
    """
    values = _metric_values(summary, telemetry)
    return [{"name": e.name, "metric": e.metric, "observed": values.get(e.metric),
             "held": e.holds(values.get(e.metric))} for e in scenario.checked_expectations]


def energy_per_robot(scenario: Scenario, records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Robot energy per robot and tier (J), from the energy model.

    When records carry ``energy_j`` (the robot's own ledger), those are summed.
    Otherwise each request is costed with the thesis model and measured inputs:
    a remote answer costs ``P_i * ToR + P_u * bytes_up / B_u + P_d *
    bytes_down / B_d`` (Eq 4.3-4.4 with the measured wait instead of ``C /
    S_c``; B_u, B_d = the thesis's 23 and 28 Mb/s); a local answer costs
    ``P_c * ToR`` (measured compute time).  Robots without a known profile are
    skipped.  Returns ``{}`` when the energy package is missing.
    """
    try:
        from scmr_mesh.energy import get_profile
        from scmr_mesh.energy.model import e_trans
    except ImportError:  # pragma: no cover - energy area absent
        return {}
    up_bps, down_bps = 23 * 131072, 28 * 131072
    out: dict[str, Any] = {}
    for r in scenario.robots:
        if not r.profile:
            continue
        try:
            prof = get_profile(r.profile)
        except Exception as exc:  # noqa: BLE001 - unknown profile: report, do not fail
            out[r.id] = {"profile": r.profile, "error": str(exc)}
            continue
        per_tier: dict[str, float] = {}
        source = "model"
        for rec in records:
            if str(rec.get("robot")) != r.id or not rec.get("ok"):
                continue
            tier = rec.get("tier") or "unknown"
            if rec.get("energy_j") is not None:
                e = float(rec["energy_j"])
                source = "robot ledger"
            else:
                tor_s = float(rec.get("tor_ms") or 0.0) / 1000.0
                if tier == "local":
                    e = prof.p_compute_w * tor_s
                else:
                    e = prof.p_idle_w * tor_s + e_trans(
                        float(rec.get("bytes_up") or 0), float(rec.get("bytes_down") or 0),
                        p_up_w=prof.p_up_w, p_down_w=prof.p_down_w, up_Bps=up_bps, down_Bps=down_bps)
            per_tier[tier] = per_tier.get(tier, 0.0) + e
        out[r.id] = {"profile": r.profile, "source": source, "total_j": sum(per_tier.values()),
                     "per_tier_j": per_tier}
    return out


def thesis_table(path: Path | None) -> dict[str, Any] | None:
    """Per-robot figures of the thesis's Table 4.2 (ms): cloud ToR and leader processing.

    Cloud ToR of an image = download end - upload start; leader = the R2R
    processing column.  ``None`` when the CSV is not found.
    """
    if path is None or not Path(path).is_file():
        return None
    rows = list(csv.DictReader(Path(path).open(encoding="utf-8")))
    per: dict[str, dict[str, list[float]]] = {}
    for row in rows:
        robot = row["robot"].lower().replace(" ", "")
        d = per.setdefault(robot, {"cloud_tor_ms": [], "leader_ms": [], "bytes": []})
        d["cloud_tor_ms"].append(float(row["download_end_ms"]) - float(row["upload_start_ms"]))
        d["leader_ms"].append(float(row["r2r_leader_processing_ms"]))
        d["bytes"].append(float(row["original_bytes"]))
    from scmr_mesh.qos.metrics import percentile

    return {k: {"images": len(v["bytes"]), "mean_bytes": sum(v["bytes"]) / len(v["bytes"]),
                "cloud_tor_p50_ms": percentile(v["cloud_tor_ms"], 50),
                "leader_p50_ms": percentile(v["leader_ms"], 50)} for k, v in sorted(per.items())}


def build_report(
    scenario: Scenario,
    records: Sequence[Mapping[str, Any]],
    faults: Sequence[Mapping[str, Any]],
    *,
    t0_unix_ns: int,
    backend: str,
    notes: Sequence[str] = (),
    thesis_csv: Path | None = None,
    telemetry: Mapping[str, Any] | None = None,
    leadership: Mapping[str, Any] | None = None,
    topology: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The report as a JSON-able dict (pure).

    Parameters
    ----------
    scenario : Scenario
    records : sequence of dict
        The robots' ``records.jsonl`` rows.
    faults : sequence of dict
        Faults as :func:`scmr_mesh.qos.metrics.summarize` takes them, plus
        ``kind``, ``label``, ``at_s``.
    t0_unix_ns : int, keyword-only
        When the robots started (time 0 of the timeline).
    backend : str, keyword-only
    notes : sequence of str, keyword-only
        Backend notes (skipped faults...).
    thesis_csv : Path, keyword-only
        ``thesis_table_4_2.csv`` to put beside our figures.
    telemetry : dict, keyword-only
        The data tier's count (``RunResult.telemetry``: ``{"sent", "stored",
        "duplicates", "lost", "per_robot"}``), checked by the default
        expectation ``telemetry_lost <= 0`` (None: not counted, which fails
        it); when None, :func:`write_report` still takes it from the run's
        ``telemetry.json`` for the report's table.
    leadership, topology : dict, keyword-only
        ``RunResult.leadership()`` and ``RunResult.topology`` (docs/R2R.md).

    Returns
    -------
    dict
        ``{"scenario", "seed", "backend", "summary", "per_robot", "per_tier",
        "faults", "expectations", "passed", "energy", "thesis", "notes",
        "telemetry", "requests"}``.
    """
    from scmr_mesh.qos.metrics import summarize

    summ = summarize(records, faults, robots=len(scenario.robots))
    from scmr_mesh.scenario.livegraph import LiveGraph, alone_with_path, reroutes, split_leader_ms

    graph = LiveGraph(scenario, faults, t0_unix_ns)
    rr_all = reroutes(graph, records, radio=True)
    rerouted = dict(zip(graph.keys, rr_all))
    radio_rr = [r for r in rr_all[len(graph.keys):] if r["reroute_ms"] or r["no_path"]]
    faults_out = []
    robot_ids = {r.id for r in scenario.robots}
    for f in summ["faults"]:
        # requests of the robots the fault touches, sent while it was active
        who = set(f.get("robots") or []) or (set(f.get("link") or ()) & robot_ids) or robot_ids
        a = int(f["start_unix_ns"])
        b = int(f["end_unix_ns"]) if f.get("end_unix_ns") is not None else None
        window = [r for r in records if str(r.get("robot")) in who and r.get("sent_unix_ns") is not None
                  and int(r["sent_unix_ns"]) >= a and (b is None or int(r["sent_unix_ns"]) < b)]
        from scmr_mesh.qos.metrics import tier_counts, tor_summary

        during = {"robots": sorted(who), "requests": len(window), "tor_ms": tor_summary(window),
                  "by_tier": tier_counts(window)}
        faults_out.append({
            "kind": f.get("kind"), "label": f.get("label"), "at_s": f.get("at_s"), "for_s": f.get("for_s"),
            "tier": f.get("tier"), "robots": f.get("robots"),
            "started_at_s": (int(f["start_unix_ns"]) - t0_unix_ns) / 1e9,
            "ended_at_s": None if f.get("end_unix_ns") is None else (int(f["end_unix_ns"]) - t0_unix_ns) / 1e9,
            "failover_gap_ms": f.get("failover_gap_ms"), "failover_by_robot": f.get("failover_by_robot"),
            "failback_gap_ms": f.get("failback_gap_ms"), "notes": f.get("notes", []), "during": during,
            "restart_ready_after_ms": None if f.get("ready_unix_ns") is None or f.get("end_unix_ns") is None
            else (int(f["ready_unix_ns"]) - int(f["end_unix_ns"])) / 1e6,
            **rerouted.get((str(f.get("label", "")), int(f["start_unix_ns"])),
                           {"reroute_ms": {}, "no_path": [], "reroute_max_ms": None}),
        })
    links = links_over_time(scenario)
    requests = []
    for r in records:
        row = {k: r.get(k) for k in REQUEST_FIELDS}
        if r.get("sent_unix_ns") is not None:
            row["sent_s"] = (int(r["sent_unix_ns"]) - t0_unix_ns) / 1e9
        row["hops"] = request_hops(scenario, links, row, graph)
        requests.append(row)
    multihop = {
        "max_hops": max((q["hops"] for q in requests if q["hops"] is not None), default=None),
        "alone_with_path": alone_with_path(graph, records),
        "max_reroute_ms": _max_reroute(faults_out + radio_rr),
        "radio_reroutes": radio_rr,
        "split_leader_ms": None if leadership is None else split_leader_ms(
            graph, leadership.get("leaders_over_time") or [], scenario.duration_s),
    }
    expectations = check_expectations(scenario, {**summ, "leadership": leadership, "multihop": multihop}, telemetry)
    return {
        "scenario": scenario.name,
        "description": scenario.description,
        "source": scenario.source,
        "seed": scenario.seed,
        "backend": backend,
        "duration_s": scenario.duration_s,
        "lease_ms": scenario.lease_ms,
        "process": scenario.process or "drivable pipeline",
        "t0_unix_ns": t0_unix_ns,
        "summary": {
            "requests": summ["requests"], "succeeded": summ["succeeded"], "ror": summ["ror"],
            "tor_ms": summ["tor_ms"], "by_tier": summ["by_tier"],
            "hedged": summ["hedges"]["hedged"], "hedge_won": summ["hedges"]["hedge_won"],
            "hedge_rate": summ["hedges"]["hedge_rate"],
            "hedge_duplicates_by_tier": summ["hedges"]["duplicates_by_tier"],
            "hedge_resent": summ["hedges"]["resent"],
        },
        "per_robot": summ["per_robot"],
        "per_tier": summ["per_tier"],
        "faults": faults_out,
        "expectations": expectations,
        "passed": all(e["held"] for e in expectations),
        "energy": energy_per_robot(scenario, records),
        "thesis": thesis_table(thesis_csv),
        "notes": list(notes),
        "telemetry": dict(telemetry) if telemetry is not None else None,
        "leadership": dict(leadership) if leadership is not None else None,
        "topology": dict(topology) if topology is not None else None,
        "links_over_time": links,
        "multihop": multihop,
        "requests": requests,
    }


def _max_reroute(faults_out: Sequence[Mapping[str, Any]]) -> float | None:
    """The largest reroute of any fault (0.0: no fault rerouted anyone; None: a robot never rerouted)."""
    vals = []
    for f in faults_out:
        per = f.get("reroute_ms") or {}
        if any(v is None for v in per.values()):
            return None
        vals += list(per.values())
    return max(vals) if vals else 0.0


def links_over_time(scenario: Scenario) -> list[dict[str, Any]] | None:
    """The radio link graph over time (``[{"t_s", "links"}]``), or None without a radio topology."""
    if scenario.radio is None:
        return None
    from scmr_mesh.scenario.radio import links_timeline

    return links_timeline(scenario.radio, scenario.duration_s)


def request_hops(scenario: Scenario, links: Sequence[Mapping[str, Any]] | None,
                 row: Mapping[str, Any], graph: Any = None) -> int | None:
    """Radio hops from the robot to the node that answered, when the request was sent (0: local; None: failed
    or no path).  Without a radio topology every peer links to every other: 1 hop to any server.  With
    ``graph`` (a :class:`~scmr_mesh.scenario.livegraph.LiveGraph`), over the live graph: crashed relays
    and cut links are not paths."""
    if not row.get("ok"):
        return None
    if row.get("tier") == "local":
        return 0
    node = row.get("served_by")
    if links is None or node is None or row.get("sent_s") is None:
        return 1
    if graph is not None:
        return graph.path_len(str(row.get("robot")), scenario.peer_of(str(node)), max(0.0, float(row["sent_s"])))
    from scmr_mesh.scenario.radio import hops

    now = [e for e in links if e["t_s"] <= max(0.0, float(row["sent_s"]))][-1]
    return hops([tuple(p) for p in now["links"]], str(row.get("robot")), scenario.peer_of(str(node)))


def _fmt(v: Any, nd: int = 1) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{nd}f}" if math.isfinite(v) else str(v)
    return str(v)


def _during(d: Mapping[str, Any] | None) -> str:
    if not d:
        return "-"
    tiers = ", ".join(f"{k} {v}" for k, v in d["by_tier"].items() if v)
    return f"{d['requests']} of {','.join(d['robots'])}, {_fmt(d['tor_ms'].get('p50'))}, {tiers or '-'}"


def _leadership_md(lead: Mapping[str, Any] | None, topo: Mapping[str, Any] | None) -> list[str]:
    L: list[str] = []
    if lead is not None:
        end = lead.get("leaders_at_end") or []
        L += ["", "## Leadership of the R2R tier", "",
              f"Leader at the end: **{', '.join(end) or 'none'}**"
              + (f" (**{len(end)} leaders**)" if len(end) > 1 else "")
              + ("" if lead.get("converged_after_heal_ms") is None else
                 f"; one leader {lead['converged_after_heal_ms']:.0f} ms after the heal") + ".", "",
              "| at s | from | to | term | cause | new leader after ms | robots waited ms | gap ms |",
              "|---|---|---|---|---|---|---|---|"]
        for c in lead.get("changes", []):
            L.append(f"| {_fmt(c['t_s'], 3)} | {_fmt(c['from'])} | {c['to']} | {_fmt(c.get('term'))} | {c['cause']} | "
                     f"{_fmt(c.get('succession_ms'))} | {_fmt(c.get('wait_ms'))} | {_fmt(c.get('gap_ms'))} |")
        if not lead.get("changes"):
            L.append("| (no leader was elected) | | | | | | | |")
        L += ["", "*new leader after*: from the old leader's loss to the new leader's claim; *robots waited*: the "
              "longest a robot waited for the new leader; *gap*: the largest per-robot time between the old "
              "leader's last answer and the new one's first (includes the request period)."]
    if topo:
        L += ["", "## Topology", "", "| node | role | handed | runs for the lead |", "|---|---|---|---|"]
        for n, t in topo.items():
            cap = f"yes ({t.get('capability') or 'host'})" if t.get("leader_capable") else "no"
            L.append(f"| {n} | {t['role']} | {', '.join(t['connect']) or '(listens)'} | {cap} |")
    return L


def _dups(by_tier: Mapping[str, int] | None) -> str:
    """``cloud 3, leader 1`` (``none`` when no copy was duplicate work)."""
    return ", ".join(f"{t} {n}" for t, n in (by_tier or {}).items() if n) or "none"


def markdown(report: Mapping[str, Any], *, plots: Sequence[str] = ()) -> str:
    """The report as Markdown."""
    s = report["summary"]
    L = [f"# Scenario `{report['scenario']}` ({report['backend']} backend)", ""]
    if report.get("description"):
        L += [report["description"], ""]
    L += [f"Seed {report['seed']}, duration {report['duration_s']:g} s, lease {report['lease_ms']} ms, "
          f"process {report.get('process', '-')}, "
          f"file `{report['source']}`. Result: **{'PASSED' if report['passed'] else 'FAILED'}**.", ""]
    L += ["## Expectations", "", "| expectation | observed | held |", "|---|---|---|"]
    for e in report["expectations"]:
        L.append(f"| {e['name']} | {_fmt(e['observed'])} | {'yes' if e['held'] else '**no**'} |")
    if not report["expectations"]:
        L.append("| (none) | | |")
    L += ["", "## Summary", "",
          f"{s['requests']} requests, {s['succeeded']} succeeded, RoR {_fmt(s['ror'], 3)}; "
          f"ToR p50 {_fmt(s['tor_ms'].get('p50'))} ms, p99 {_fmt(s['tor_ms'].get('p99'))} ms; "
          f"hedged {s.get('hedged', 0)}, won by the hedge {s.get('hedge_won', 0)}, hedges sent again "
          f"{s.get('hedge_resent', 0)}, duplicate work "
          f"{_dups(s.get('hedge_duplicates_by_tier'))}.", "",
          "| tier | answers | ToR p50 ms | ToR p99 ms |", "|---|---|---|---|"]
    for tier, n in s["by_tier"].items():
        t = report["per_tier"].get(tier, {})
        L.append(f"| {tier} | {n} | {_fmt(t.get('p50'))} | {_fmt(t.get('p99'))} |")
    L += ["", "### Per robot", "",
          "| robot | requests | RoR | ToR p50 ms | ToR p99 ms | cloud | leader | peer | local | failed | hedged "
          "| hedge won |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for rid, g in report["per_robot"].items():
        bt = g["by_tier"]
        L.append(f"| {rid} | {g['requests']} | {_fmt(g['ror'], 3)} | {_fmt(g['tor_ms'].get('p50'))} | "
                 f"{_fmt(g['tor_ms'].get('p99'))} | {bt.get('cloud', 0)} | {bt.get('leader', 0)} | "
                 f"{bt.get('peer', 0)} | {bt.get('local', 0)} | {bt.get('failed', 0)} | {g.get('hedged', 0)} | "
                 f"{g.get('hedge_won', 0)} |")
    L += _leadership_md(report.get("leadership"), report.get("topology"))
    L += ["", "## Faults", "", "| fault | applied at s | lifted at s | tier lost | failover gap ms | failback gap ms "
          "| during: requests, ToR p50 ms, tiers |", "|---|---|---|---|---|---|---|"]
    for f in report["faults"]:
        L.append(f"| {str(f['label']).replace('|', chr(92) + '|')} | {_fmt(f['started_at_s'], 3)} | {_fmt(f['ended_at_s'], 3)} | {_fmt(f['tier'])} | "
                 f"{_fmt(f['failover_gap_ms'])} | {_fmt(f['failback_gap_ms'])} | {_during(f.get('during'))} |")
    if not report["faults"]:
        L.append("| (none) | | | | | | |")
    rr = [f for f in report["faults"] if f.get("reroute_ms") or f.get("no_path")]
    if rr:
        L += ["", "Reroute (robots whose path to their server the fault broke: from the fault to their first "
              "remote answer; scmr_mesh/scenario/livegraph.py):", "", "| fault | robot | reroute ms |", "|---|---|---|"]
        for f in rr:
            for r, v in f["reroute_ms"].items():
                L.append(f"| {str(f['label']).replace('|', chr(92) + '|')} | {r} | {_fmt(v)} |")
            for r in f.get("no_path") or []:
                L.append(f"| {str(f['label']).replace('|', chr(92) + '|')} | {r} | no path to any server |")
    mh = report.get("multihop") or {}
    if mh:
        L += ["", f"Multi-hop: most radio hops to a server {_fmt(mh.get('max_hops'))}; frames computed alone with a "
              f"path to a server {_fmt(mh.get('alone_with_path'))}; longest reroute {_fmt(mh.get('max_reroute_ms'))} "
              f"ms; longest time a connected part had two leaders {_fmt(mh.get('split_leader_ms'))} ms."]
    for f in report["faults"]:
        if f.get("restart_ready_after_ms") is not None:
            L += ["", f"{f['label']}: the restarted peer was ready {f['restart_ready_after_ms']:.0f} ms after its "
                  "restart (process start-up, part of the failback gap)."]
    L += ["", "Failover gap per robot: from the later of the fault and the sending of the robot's first request the "
          "lost tier failed to answer, to that robot's first fallback answer (largest per fault). Failback: from the "
          "link's return / the restart to the first answer of the restored tier (scmr_mesh.qos.metrics).", ""]
    energy = report.get("energy") or {}
    energy = energy.get("per_robot", {}) if "per_robot" in energy else energy  # run_report's, or build_report's
    if energy:
        L += ["## Energy per robot", "", "| robot | profile | total J | per tier J | source |", "|---|---|---|---|---|"]
        for rid, e in energy.items():
            if "error" in e:
                L.append(f"| {rid} | {e['profile']} | - | {e['error']} | |")
                continue
            per = ", ".join(f"{k} {v:.2f}" for k, v in (e.get("per_tier_j") or {}).items())
            L.append(f"| {rid} | {e['profile']} | {e['total_j']:.2f} | {per} | {e.get('source', 'robot ledger')} |")
        L += ["", "Model: remote answer = P_i x ToR + P_u x bytes_up / 23 Mb/s + P_d x bytes_down / 28 Mb/s "
              "(Eq 4.3-4.4, measured wait); local = P_c x ToR. Table 4.3 profiles.", ""]
    if report.get("thesis"):
        L += ["## Beside the thesis (Table 4.2)", "",
              "| robot | thesis images | thesis mean bytes | thesis cloud ToR p50 ms | thesis leader p50 ms | "
              "our ToR p50 ms | our cloud p50 ms | our leader p50 ms |", "|---|---|---|---|---|---|---|---|"]
        recs = request_rows(report)
        from scmr_mesh.qos.metrics import tor_summary

        for rid, t in report["thesis"].items():
            mine = [r for r in recs if str(r.get("robot")) == rid]
            ours = report["per_robot"].get(rid, {}).get("tor_ms", {})
            cl = tor_summary([r for r in mine if r.get("tier") == "cloud"])
            le = tor_summary([r for r in mine if r.get("tier") == "leader"])
            L.append(f"| {rid} | {t['images']} | {t['mean_bytes']:.0f} | {t['cloud_tor_p50_ms']:.0f} | "
                     f"{t['leader_p50_ms']:.0f} | {_fmt(ours.get('p50'))} | {_fmt(cl['p50'])} | {_fmt(le['p50'])} |")
        L.append("")
    tel = report.get("telemetry")
    if tel:
        L += ["## Telemetry (data tier)", "",
              f"{tel.get('sent', 0)} sent, {tel.get('stored', 0)} stored, {tel.get('duplicates', 0)} duplicates, "
              f"{tel.get('queued', 0)} queued, **{tel.get('lost', 0)} lost** (over seqs 1..sent: queued = still on "
              "a robot's disk when it stopped, sent at its next start; lost = neither stored nor queued; "
              "docs/DATA.md).", "",
              "| robot | sent | stored | duplicates | lost | lost seqs | queued |", "|---|---|---|---|---|---|---|"]
        for rid, t in (tel.get("per_robot") or {}).items():
            L.append(f"| {rid} | {t.get('sent', 0)} | {t.get('stored', 0)} | {t.get('duplicates', 0)} | "
                     f"{t.get('lost', 0)} | {', '.join(t.get('missing') or []) or '-'} | {_fmt(t.get('queued'))} |")
        L.append("")
    if report.get("notes"):
        L += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    if plots:
        L += ["## Plots", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in plots] + [""]
    L += ["## Requests", "", "| robot | seq | image | bytes up | bytes down | sent s | ToR ms | ok | tier | served by |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in request_rows(report):
        L.append(f"| {r['robot']} | {_fmt(r['seq'])} | {_fmt(r['image'])} | {_fmt(r['bytes_up'])} | "
                 f"{_fmt(r['bytes_down'])} | {_fmt(r.get('sent_s'), 3)} | {_fmt(r['tor_ms'])} | {_fmt(r['ok'])} | "
                 f"{_fmt(r['tier'])} | {_fmt(r['served_by'])} |")
    return "\n".join(L) + "\n"


# -- plots (OpenCV) --------------------------------------------------------
def write_report(report: Mapping[str, Any], out_dir: Path, *, json_path: Path | None = None) -> dict[str, Path]:
    """Write ``report.json``, ``report.md``, ``tor.png`` and ``tiers.png`` into ``out_dir``.

    Returns the paths written (``json`` is ``json_path`` when given).  A report
    without telemetry gets the run's ``out_dir/telemetry.json`` (written by the
    runner) when there is one.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if report.get("telemetry") is None and (out_dir / "telemetry.json").is_file():
        try:
            report = {**report, "telemetry": json.loads((out_dir / "telemetry.json").read_text())}
        except ValueError as exc:
            log.warning("%s is not JSON (%s): report without telemetry", out_dir / "telemetry.json", exc)
    paths = {"tor_png": out_dir / "tor.png", "tiers_png": out_dir / "tiers.png"}
    try:
        plot_tor(report, paths["tor_png"])
        plot_tiers(report, paths["tiers_png"])
        plots = [str(paths["tor_png"]), str(paths["tiers_png"])]
    except Exception as exc:  # noqa: BLE001 - plots are a bonus; never lose the report
        log.warning("plots not drawn: %s", exc)
        plots = []
    jp = Path(json_path) if json_path else out_dir / "report.json"
    jp.parent.mkdir(parents=True, exist_ok=True)
    jp.write_text(json.dumps(report, indent=2, default=str) + "\n")
    md = out_dir / "report.md"
    md.write_text(markdown(report, plots=plots))
    paths.update({"json": jp, "md": md})
    return paths


#: The schema every run report is validated against (``scmr up``, ``scmr demo``, ``scmr scenario run``).
REPORT_SCHEMA = Path(__file__).resolve().parents[2] / "schemas" / "report.schema.json"


def validate_report(report: Mapping[str, Any]) -> None:
    """Check ``report`` against ``schemas/report.schema.json``.

    Raises
    ------
    MeshError
        Naming the first field that does not match (a bug in the report code).
    """
    import jsonschema

    from scmr_mesh.errors import MeshError

    try:
        schema = json.loads(REPORT_SCHEMA.read_text())
    except OSError as exc:
        raise MeshError(f"report schema missing at {REPORT_SCHEMA}: {exc}") from None
    errs = sorted(jsonschema.Draft202012Validator(schema).iter_errors(report), key=lambda e: list(e.path))
    if errs:
        e = errs[0]
        where = "/".join(str(x) for x in e.path) or "(top)"
        raise MeshError(f"report does not match schemas/report.schema.json at {where}: {e.message}")


def run_problems(report: Mapping[str, Any]) -> list[str]:
    """What went wrong in a run besides failed requests, one sentence each (pure).

    A restarted peer that never became ready, a peer that exited with a
    non-zero status (other than one a fault killed), replies that did not
    answer the request they came for (``mismatched``), the run's PostgreSQL
    dying (restarted or not), telemetry that was lost or could not be counted.  An interrupted run lists what it saw too.
    ``scmr up`` and ``scmr demo`` print these and exit 1 when there is any
    (docs/FLEET.md).
    """
    out: list[str] = []
    t0 = report.get("started_unix_ns") or 0
    peers = report.get("peers") or {}
    topo = report.get("topology") or {}
    for f in report.get("faults") or []:
        if f.get("kind") != "crash" or f.get("end_unix_ns") is None:
            continue  # only a crash restarts a peer (its end is the restart)
        names = list(f.get("restarted") or [])
        if not names:  # the restarted peers: every cloud node for a cloud-tier crash
            names = ([n for n in peers if (topo.get(n) or {}).get("role") == "cloud" or n.startswith("cloud")]
                     if f.get("tier") == "cloud" else [str(f.get("target"))])
        never = [n for n in names if n in peers and peers[n].get("ready_unix_ns") is None]
        if f.get("ready_unix_ns") is None and not never:
            never = names or [str(f.get("target"))]
        for name in never:
            p = peers.get(name) or {}
            rc = p.get("exit")
            label = f.get("target") if len(names) <= 1 else name
            out.append(f"{label} was restarted at {(f['end_unix_ns'] - t0) / 1e9:.2f} s but never became "
                       "ready" + (f" (it exited with status {rc})" if rc not in (None, 0) else "")
                       + (f"; see {p['log']}" if p.get("log") else ""))
    # processes a fault killed on purpose
    killed = {str(n) for f in report.get("faults") or [] if f.get("kind") == "crash"
              for n in [*(f.get("killed") or []), *([f.get(k) for k in ("peer", "target")]
                                                     if f.get("end_unix_ns") is None else [])] if n}
    for name, p in peers.items():
        rc = p.get("exit")
        if rc not in (None, 0) and not (rc == -9 and name in killed):
            what = f"killed by signal {-rc}" if rc < 0 else f"exited with status {rc}"
            out.append(f"peer {name} {what}; see {p.get('log')}")
    for o in (report.get("ods") or {}).get("outages") or []:  # the run's own PostgreSQL (scmr up --clouds N)
        rc = o.get("exit")
        what = f"was killed by signal {-rc}" if isinstance(rc, int) and rc < 0 else f"exited with status {rc}"
        out.append(f"the run's PostgreSQL data store {what} at {o.get('t_s', 0):.2f} s; "
                   + (f"restarted after {o['gap_ms']:.0f} ms" if o.get("gap_ms") is not None
                      else f"it could not be restarted ({o.get('error') or 'the run ended first'})"))
    mcap = report.get("mcap")
    if mcap:  # scmr up --mcap FILE
        if mcap.get("error"):
            out.append(f"--mcap {mcap.get('path')}: the recordings could not be merged ({mcap['error']})")
        for part, why in (mcap.get("unreadable") or {}).items():
            out.append(f"--mcap {mcap.get('path')}: {part} could not be read and is not in it ({why})")
    if report.get("mismatched"):  # a server answered with a reply to another request (issue 25 item 8)
        who = ", ".join(f"{k} {v}" for k, v in (report.get("mismatched_by_node") or {}).items())
        out.append(f"{report['mismatched']} repl{'y' if report['mismatched'] == 1 else 'ies'} did not answer the "
                   f"request they came for (robot, seq or frame digest not the request's, or not a trusted reply "
                   f"of the node asked: a replayed, forged or wrong answer, never used): {who or '?'}")
    tel = report.get("telemetry")
    if tel is None:
        out.append("telemetry was not counted (see the log of scmr up)")
    else:
        if tel.get("error"):
            out.append(f"telemetry: {tel['error']}")
        if tel.get("lost"):
            who = [f"{rid} {r['lost']} (seqs {','.join(r.get('missing') or []) or '?'})"
                   for rid, r in sorted((tel.get("per_robot") or {}).items()) if r.get("lost")]
            out.append(f"{tel['lost']} of {tel.get('sent', 0)} telemetry records lost: " + "; ".join(who))
        if tel.get("conflicts"):
            out.append(f"{tel['conflicts']} telemetry records conflicted with stored ones (a robot reused seqs)")
    return out


def run_report(res: Any, *, thesis_csv: Path | None = None, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The one report of a run (``scmr up``, ``scmr demo``, ``scmr scenario run``), validated.

    The core is :func:`scmr_mesh.qos.metrics.summarize` at the top level (what
    ``schemas/report.schema.json`` requires); the scenario's view
    (:func:`build_report`: ``summary``, expectations, per-fault ``during``...)
    and the run's facts (peers, security, topology, leadership, telemetry,
    energy, ``problems``) are beside it, and each fault carries both the core's
    fields and the scenario's.

    Parameters
    ----------
    res : scmr_mesh.scenario.runner.RunResult
    thesis_csv : Path, optional
        Table 4.2 to put beside our figures.
    extra : mapping, optional
        Fields the caller adds (``scmr up``: ``clouds``, ``ods``), before validation.
    """
    from scmr_mesh.qos import metrics

    sc = res.scenario
    faults = res.fault_records()
    leadership = res.leadership()
    view = build_report(sc, res.records, faults, t0_unix_ns=res.t0_unix_ns, backend=res.backend, notes=res.notes,
                        thesis_csv=thesis_csv, telemetry=res.telemetry, leadership=leadership,
                        topology=res.topology)
    core = metrics.summarize(res.records, faults, robots=len(sc.robots))
    for f, v in zip(sorted(core["faults"], key=lambda f: int(f["start_unix_ns"])), view["faults"]):
        f.update({k: val for k, val in v.items() if k not in f})
        f.pop("notes", None) if not f.get("notes") else None
    for f in core["faults"]:
        if f.get("ready_unix_ns") is not None and f.get("end_unix_ns") is not None:
            # split the failback gap: process start-up, then ready -> first answer
            f["restart_to_ready_ms"] = (f["ready_unix_ns"] - f["end_unix_ns"]) / 1e6
            f["failback_after_ready_ms"] = metrics.failback_gap_ms(res.records, {**f, "end_unix_ns": f["ready_unix_ns"]})
    rates = {r.rate_hz for r in sc.robots}
    view["request_log"] = view.pop("requests")  # the core's "requests" is the count
    report: dict[str, Any] = {"v": 1, "kind": "report", **view, **core}
    report.update({
        "rate_hz": rates.pop() if len(rates) == 1 else None,
        "started_unix_ns": res.t0_unix_ns,
        "ended_unix_ns": time.time_ns(),
        "wall_s": res.wall_s,
        "interrupted": res.interrupted,
        "run_dir": str(res.out_dir),
        "peers": res.peers,
        "security": "insecure" if res.insecure else "mtls+acl",
        "energy": energy_report(sc, res.records),
        "hosts": host_costs(sc, getattr(res, "costs", None) or {}),
    })
    if report["rate_hz"] is None:
        del report["rate_hz"]
    report.update(extra or {})
    report["problems"] = run_problems(report)
    validate_report(report)
    return report


def host_costs(scenario: Scenario, costs: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The report's ``hosts``: the network's shape and what each host cost (``RunResult.costs``).

    ``per_host``: peak RSS (MB), CPU (s), open sockets and, on netns, TCP links to other hosts, per
    peer (its router included under ``shape = "routers"``; a router shared by a whole host has its own
    entry); ``robot_mean``: the same averaged over robots.
    """
    robots = [costs[r.id] for r in scenario.robots if r.id in costs]
    mean = {}
    for k in ("peak_rss_mb", "cpu_s", "links", "sockets"):
        vals = [c[k] for c in robots if c.get(k) is not None]
        if vals:
            mean[k] = round(sum(vals) / len(vals), 2)
    return {"shape": scenario.shape, "per_host": {k: dict(v) for k, v in costs.items()}, "robot_mean": mean}


def energy_report(scenario: Scenario, records: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """The report's ``energy``: where each robot with a profile ran its tasks and what it cost (None: no profile).

    ``per_robot`` joins the robots' own ledgers (:func:`scmr_mesh.energy.measure.energy_by_robot`)
    with the model's costing of robots that kept none (:func:`energy_per_robot`).
    """
    profiles = {r.id: r.profile for r in scenario.robots if r.profile}
    if not profiles:
        return None
    from scmr_mesh.energy.measure import energy_by_robot

    per = energy_by_robot(records, profiles)
    for rid, e in energy_per_robot(scenario, records).items():
        per.setdefault(rid, {}).update({k: v for k, v in e.items() if k not in per[rid] or not per[rid]["costed"]})
    placed = any(r.energy_placement for r in scenario.robots)
    return {"placement": "energy model (Eq 4.2-4.6), Table 4.3 profiles" if placed
            else "none (profiles only cost the requests)", "per_robot": per}
