"""``report.md`` and ``report.json`` of ``scmr thesis`` (pure: the Markdown is a function of the JSON)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Mapping


def verdict(h: Any) -> str:
    if h is True:
        return "**holds**"
    if h is False:
        return "**does not hold**"
    return f"*{h}*" if h is not None else "-"


def _f(v: Any, nd: int = 1) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.{nd}f}" if abs(v) < 1e5 else f"{v:.3g}"
    return str(v)


def _quote(c: Mapping[str, Any]) -> list[str]:
    return [f"> {c['quote']}", ">", f"> (thesis {c['source']})"]


def _one_line(e: Mapping[str, Any], limit: int = 220) -> str:
    first = str(e.get("why", "")).split(". ")[0]
    if len(first) <= limit:
        return first
    return first[:first.rfind(" ", 0, limit)] + " ..."


def _visual_table(rows: list[dict], leader: bool) -> list[str]:
    L = ["| robot | image | bytes | answers | bottom-centre drivable | thesis mode | IoU | thesis mode IoU | "
         "= pipeline here |" + (" = cloud's mask |" if leader else ""),
         "|---|---|---|---|---|---|---|---|---|" + ("---|" if leader else "")]
    for r in rows:
        L.append(f"| {r['robot']} | {r['image']} | {r['bytes']} | {r['answers']} | {_f(r['bottom_centre_drivable'], 2)} | "
                 f"{_f(r['thesis_mode_bottom_centre_drivable'], 2)} | {_f(r.get('iou'), 3)} | "
                 f"{_f(r.get('thesis_mode_iou'), 3)} | {_f(r['same_as_here'])} |"
                 + (f" {_f(r.get('same_as_cloud'))} |" if leader else ""))
    return L


def _table42(rows: list[dict], leader: bool) -> list[str]:
    L = ["| robot | our image | bytes | our cloud ToR p50 ms | server ms | comm ms |"
         + (" our leader ToR p50 ms |" if leader else "")
         + " thesis image | thesis bytes | thesis cloud ToR ms | thesis R2C ms |" + (" thesis R2R leader ms |" if leader else ""),
         "|---|---|---|---|---|---|" + ("---|" if leader else "") + "---|---|---|---|" + ("---|" if leader else "")]
    for r in rows:
        L.append(f"| {r['robot']} | {r['image']} | {_f(r['bytes'])} | {_f(r['cloud_tor_p50_ms'])} | "
                 f"{_f(r['server_p50_ms'])} | {_f(r['comm_p50_ms'])} |"
                 + (f" {_f(r['leader_tor_p50_ms'])} |" if leader else "")
                 + f" {r['thesis_image'] or '-'} ({r['thesis_description'] or '-'}) | {_f(r['thesis_bytes'])} | "
                 f"{_f(r['thesis_cloud_tor_ms'])} | {_f(r['thesis_r2c_processing_ms'])} |"
                 + (f" {_f(r['thesis_r2r_leader_ms'])} |" if leader else ""))
    return L


def _checks(e: Mapping[str, Any]) -> list[str]:
    L = []
    for c in e.get("checks", []):
        L += ["", f"- Also (thesis {c['claim']['source']}): \"{c['claim']['quote']}\"",
              f"  Verdict: {verdict(c['holds'])}. {c['why']}"]
    return L


def _inputs(e: Mapping[str, Any]) -> list[str]:
    inp = e.get("inputs") or {}
    L = ["", "<details><summary>inputs</summary>", "",
         "measured: " + ", ".join(f"`{m}`" for m in inp.get("measured", [])),
         "", "cited (facts.toml / table_4_2.csv): " + ", ".join(inp.get("cited", []))]
    for k, a in (inp.get("assumed") or {}).items():
        L.append(f"\nassumed `{k}` = {a['value']}: {a['why']}")
    return L + ["", "</details>"]


def _figs(e: Mapping[str, Any]) -> list[str]:
    return ["", *[f"![{Path(p).stem}]({p})" for p in e.get("figures", [])]] if e.get("figures") else []


def markdown(rep: Mapping[str, Any]) -> str:
    cfg, host, t = rep["config"], rep["host"], rep.get("timing", {})
    ex = rep["experiments"]
    L = ["# The dissertation, reproduced: `scmr thesis`" + (" --quick" if cfg.get("quick") else ""), "",
         "Experiments 1-7 of *Survivable Cloud Multi-Robotics Framework for Heterogeneous Environments* (chapter 4) "
         "run on this machine against real peers, with the thesis's published figures beside ours "
         "(claims quoted from `scmr_mesh/thesis/facts.toml` and `table_4_2.csv`, each with its table or figure).", "",
         f"Machine: {host.get('cpus')} CPUs ({host.get('cpu_model')}), clock {_f(host.get('clock_hz', 0) / 1e9, 3)} GHz "
         f"({host.get('clock_source')}); load average at the start {host.get('loadavg_at_start')}, after the runs "
         f"{host.get('loadavg_after_runs')}. Backend `{cfg.get('backend')}`; {cfg.get('robots')} robots x "
         f"{cfg.get('images')} images; time unit {cfg.get('step_s')} s; fleet sizes {cfg.get('fleet_sizes')}. "
         f"Every fleet run serves pipeline mode `{rep['served_mode']}` (the robots' default); experiments 1 and 4 also "
         "show mode `thesis` (the literal dissertation rules) computed on the same frames.", "",
         f"Duration: estimated {_f(t.get('estimate_s'), 0)} s up front, fleet runs {_f(t.get('runs_s'), 0)} s, "
         f"total {_f(t.get('total_s'), 0)} s. Timings were measured on a shared machine: see the load averages.", "",
         "## Verdicts", "", "| # | the thesis says (source) | ours | verdict |", "|---|---|---|---|"]
    for k in sorted(ex, key=int):
        e = ex[k]
        L.append(f"| {k} | {e['claim']['source']}: {e['claim']['quote'][:110]}... | {_one_line(e)} | "
                 f"{verdict(e['holds'])} |")
    t44 = rep["model"]["table_4_4"]
    for name, h in t44["holds"].items():
        L.append(f"| T4.4 | {t44['claim']['source']}: {name} | chosen fit: "
                 f"{t44['r2c_fit' if name.startswith('r2c') else 'r2r_fit']['chosen']} | {verdict(h)} |")
    for k in sorted(ex, key=int):
        e = ex[k]
        L += ["", f"## Experiment {k}: {e['title']}", "", *_quote(e["claim"]), "",
              f"**Ours.** {e['why']}", "", f"**Verdict: {verdict(e['holds'])}.**"]
        L += _checks(e)
        o = e["ours"]
        if k in ("1", "4"):
            L += ["", *_visual_table(o["per_image"], k == "4")]
        if k in ("2", "5"):
            L += ["", "Beside thesis Table 4.2 (our images in the thesis's order per robot; *comm* = ToR - server time):",
                  "", *_table42(o["per_image"], k == "5")]
        if k == "3":
            L += ["", "| profile | P_c W | J per cloud answer (same frames) |", "|---|---|---|"]
            for p in o["order_by_p_compute"]:
                L.append(f"| {p} | {_f(o['p_compute_w'][p], 0)} | {_f(o['energy_per_request_same_frames_j'][p], 4)} |")
            srv = e["checks"][1]["ours"]["cloud_vs_robots"]
            L += ["", "Cloud as server (measured CPU time, Table 4.3 leader powers):", "",
                  "| robots | frames | CPU s | window s | serving W | serving J per frame | energy J |",
                  "|---|---|---|---|---|---|---|"]
            for s in srv:
                L.append(f"| {s['robots']} | {s['frames']} | {_f(s['cpu_s'], 3)} | {_f(s['window_s'], 2)} | "
                         f"{_f(s['serving_w'], 2)} | {_f(s['serving_j_per_frame'], 3)} | {_f(s['energy_j'], 1)} |")
        if k == "6":
            L += ["", "| stage k (robots cut) | from s | to s | leader frames | leader serving W | cloud frames | "
                  "cloud serving W |", "|---|---|---|---|---|---|---|"]
            for s in o["stages"]:
                le, cl = s.get("leader", {}), s.get("cloud", {})
                L.append(f"| {s['k']} | {_f(s['from_s'], 2)} | {_f(s['to_s'], 2)} | {le.get('frames', '-')} | "
                         f"{_f(le.get('serving_w'), 2)} | {cl.get('frames', '-')} | {_f(cl.get('serving_w'), 2)} |")
        if k == "7":
            L += ["", "| profile | 1 MB break-even Mb/s | 3 MB break-even Mb/s | with measured C and frames Mb/s |",
                  "|---|---|---|---|"]
            for p, b in o["break_even_mbps"].items():
                vals = list(b.values())
                L.append(f"| {p} | {_f(vals[0], 2)} | {_f(vals[1], 2)} | "
                         f"{_f(o['measured_inputs']['break_even_mbps'].get(p), 2)} |")
        L += _figs(e)
        L += _inputs(e)
    m = rep["model"]
    L += ["", "## Table 4.4: communication delay", "", *_quote(t44["claim"]), "", t44["why"], "",
          "| robots | our CPU share | load after | R2C answers | R2C comm p50 ms | R2C ToR p50 ms | R2R answers | "
          "R2R comm p50 ms | R2R ToR p50 ms |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in t44["per_fleet_size"]:
        L.append(f"| {r['robots']} | {_f(r.get('fleet_cpu_share'), 2)}{' (CPU-bound)' if r.get('cpu_bound') else ''} | "
                 f"{(r.get('loadavg_after') or ['-'])[0]} | {r['r2c_n']} | {_f(r['r2c_comm_p50_ms'], 2)} | "
                 f"{_f(r['r2c_tor_p50_ms'], 2)} | {r['r2r_n']} | {_f(r['r2r_comm_p50_ms'], 2)} | "
                 f"{_f(r['r2r_tor_p50_ms'], 2)} |")
    for tier in ("r2c", "r2r"):
        for key, what in ((f"{tier}_fit", "sizes not CPU-bound"), (f"{tier}_fit_all_sizes", "every size")):
            ch = t44.get(key)
            if not ch:
                continue
            L += ["", f"{tier.upper()} fits, {what} (leave-one-out RMSE ms; chosen **{ch['chosen']}**): " + "; ".join(
                f"{mname}: {fv['formula']}, a {_f(fv['a'], 3)}, b {_f(fv.get('b'), 3)}, R^2 {_f(fv['r2'], 3)}, "
                f"LOO {_f(fv['loo_rmse'], 3)}" for mname, fv in ch["fits"].items())]
    cb = t44.get("comm_vs_bytes")
    if cb:
        L += ["", f"Against the frame size (every first-attempt cloud answer): {cb['formula']}, a {cb['a_ms']} ms, "
              f"b {cb['b_ms_per_100kB']} +- {cb['b_se_ms_per_100kB']} ms per 100 kB, R^2 {cb['r2']}, n {cb['n']}."]
    L += ["", "Verdicts: " + "; ".join(f"{k} {verdict(v)}" for k, v in t44["holds"].items()) + "."]
    L += _figs(t44) + _inputs(t44)
    for key in ("eq_3_14", "eq_3_18_19"):
        e = m[key]
        L += ["", f"## {e['title']}", "", *_quote(e["claim"]), "", e["why"]]
        if e.get("ours"):
            L += ["", "```", json.dumps(e["ours"], indent=1), "```"]
        L += _inputs(e)
    L += ["", "## Runs", "", "| run | scenario | backend | robots | s | requests | RoR | telemetry lost | wall s | faults |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rep["runs"].items():
        L.append(f"| {name} | {r['scenario']} | {r['backend']} | {r['robots']} | {r['duration_s']:g} | {r['requests']} | "
                 f"{_f(r['ror'], 3)} | {_f(r['telemetry_lost'])} | {_f(r['wall_s'], 0)} | "
                 f"{'; '.join(r['faults']) or '-'} |")
    losses = [f"{n}: RoR {r['ror']}" for n, r in rep["runs"].items() if r.get("ror") is not None and r["ror"] < 1]
    losses += [f"{n}: {r['telemetry_lost']} telemetry records lost (sent by robots, never stored by a cloud; "
               f"runs/{n}/telemetry.json)" for n, r in rep["runs"].items() if r.get("telemetry_lost")]
    if losses:
        L += ["", "**Losses:**", *[f"- {x}" for x in losses]]
    notes = [f"{n}: {x}" for n, r in rep["runs"].items() for x in r.get("notes", [])]
    if notes:
        L += ["", "Notes:", *[f"- {n}" for n in notes]]
    L += ["", "Raw data: `runs/<run>/` (run.json, cpu.json, robots' records and masks, peer logs, the scenario's own "
          "report). `scmr thesis --reanalyse --out DIR` rebuilds this report from them."]
    return "\n".join(L) + "\n"


def write(rep: Mapping[str, Any], out: Path) -> dict[str, Path]:
    """Write ``report.json`` and ``report.md`` into ``out``."""
    out = Path(out)
    rep = dict(rep)
    rep.setdefault("written_unix", round(time.time(), 3))
    (out / "report.json").write_text(json.dumps(rep, indent=1, default=str) + "\n")
    (out / "report.md").write_text(markdown(rep))
    return {"json": out / "report.json", "md": out / "report.md"}
