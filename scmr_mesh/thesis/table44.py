"""Table 4.4: service time against frame size, fitted.

A mixin of :class:`scmr_mesh.thesis.analysis.Builder` (``self``: the builder with its runs).
"""

from __future__ import annotations

import logging
from typing import Any

from scmr_mesh.thesis import fit as fitting
from scmr_mesh.thesis.cpu import cpu_between, peer_series
from scmr_mesh.thesis.common import CPU_BOUND, _claim, _median, _r, _single, comm_ms, in_window

log = logging.getLogger(__name__)


class Table44Mixin:
    """Table 4.4: service time against frame size, fitted."""

    def table_4_4(self) -> dict[str, Any]:
        f = self.facts
        rows = []
        for n, run in self.size_runs():
            cut = self._cut(run)
            r2c = [r for r in run.records if r.get("tier") == "cloud" and _single(r) and in_window(r, run.t0, cut)]
            r2r = [r for r in run.records if r.get("tier") == "leader" and _single(r)
                   and in_window(r, cut, self._heal(run))]
            used = [cpu_between(peer_series(run.cpu, p), run.t0, run.end) for p in run.cpu.get("series", {})]
            util = sum(u for u in used if u is not None) / ((run.end - run.t0) / 1e9 * self.cpus)
            rows.append({"robots": n, "fleet_cpu_share": _r(util), "cpu_bound": util > CPU_BOUND,
                         "loadavg_after": (run.info.get("loadavg") or {}).get("after"),
                         "r2c_n": len(r2c), "r2c_comm_p50_ms": _r(_median([comm_ms(r) for r in r2c])),
                         "r2c_tor_p50_ms": _r(_median([r["tor_ms"] for r in r2c])),
                         "r2r_n": len(r2r), "r2r_comm_p50_ms": _r(_median([comm_ms(r) for r in r2r])),
                         "r2r_tor_p50_ms": _r(_median([r["tor_ms"] for r in r2r]))})
        out: dict[str, Any] = {"title": "Table 4.4: communication delay against fleet size and image size",
                               "claim": _claim(f["table44"], m=f["table44_m"].values["m"]), "per_fleet_size": rows}
        verdicts = {}
        free = [r for r in rows if not r["cpu_bound"]]
        for tier in ("r2c", "r2r"):
            def pick(rs):
                pts = [(r["robots"], r[f"{tier}_comm_p50_ms"]) for r in rs if r[f"{tier}_comm_p50_ms"] is not None]
                return fitting.choose([p[0] for p in pts], [p[1] for p in pts], ("const", "log", "linear")) \
                    if len(pts) >= 3 else {"chosen": None, "fits": {}}

            ch, ch_all = pick(free), pick(rows)
            out[f"{tier}_fit"] = ch
            out[f"{tier}_fit_all_sizes"] = ch_all
            if ch["chosen"] is None:
                verdicts[tier] = ("not comparable: fewer than three fleet sizes with answers" if len(free) == len(rows)
                                  else "not comparable: fewer than three fleet sizes in which the host was not "
                                       "CPU-bound")
            elif tier == "r2c":
                verdicts[tier] = ch["chosen"] == "const"
            else:
                verdicts[tier] = ch["chosen"] in ("const", "log")
        # against image size: every single-attempt cloud answer of every run
        xs, ys = [], []
        for run in self.runs.values():
            for r in run.records:
                if r.get("tier") == "cloud" and _single(r) and comm_ms(r) is not None:
                    xs.append(int(r["bytes_up"]))
                    ys.append(comm_ms(r))
        size_fit = fitting.fit("linear", xs, ys) if len(set(xs)) >= 2 else None
        out["comm_vs_bytes"] = None if size_fit is None else {
            "formula": "comm_ms = a + b * bytes", "a_ms": _r(size_fit["a"]), "b_ms_per_100kB": _r(size_fit["b"] * 1e5, 4),
            "b_se_ms_per_100kB": _r((size_fit["slope_se"] or 0) * 1e5, 4), "r2": _r(size_fit["r2"]), "n": size_fit["n"]}
        out["holds"] = {"r2c_O(1)": verdicts["r2c"], "r2r_O(M log N)": verdicts["r2r"]}
        bound = [r["robots"] for r in rows if r["cpu_bound"]]
        out["why"] = (
            "communication delay = ToR - server_ms of requests answered at the first attempt (transfer, routing, the "
            "robot's own encode and decode), median per fleet size; leave-one-out picks among y = a, a + b log2 N and "
            f"a + b N over the fleet sizes in which our own processes used at most {CPU_BOUND:.0%} of the host's CPU "
            + (f"(left out, CPU-bound: N = {', '.join(map(str, bound))})" if bound else "(all of them)")
            + f": R2C {out['r2c_fit']['chosen']}, R2R (M = 1) {out['r2r_fit']['chosen']}; over every size: R2C "
            f"{out['r2c_fit_all_sizes']['chosen']}, R2R {out['r2r_fit_all_sizes']['chosen']}. In this mesh a robot "
            "reaches the cloud and the leader in one hop (gossip only spreads locators), so both tiers are O(1) in "
            "hops; what grows with N on one 2-core host is CPU contention (N robot processes and the servers share "
            "two cores with other work: see each run's load average).")
        out["figures"] = self.fig(lambda: self._fig_table44(rows, out, xs, ys, size_fit), "table44_delay.png")
        out["inputs"] = {"measured": [f"runs/{r.name}/" for _, r in self.size_runs()] + ["runs/*/ (records.jsonl)"],
                         "cited": ["table44", "table44_m"], "assumed": {}}
        return out


    def _fig_table44(self, rows, out, xs, ys, size_fit):
        import numpy as np

        from scmr_mesh.thesis.figures import BLUE, ORANGE, RED, Chart, hstack

        c1 = Chart("Communication delay vs fleet size (Table 4.4)", "robots N", "ms (ToR - server_ms, p50)", width=580)
        for tier, colour in (("r2c", BLUE), ("r2r", ORANGE)):
            pts = [(r["robots"], r[f"{tier}_comm_p50_ms"]) for r in rows
                   if r[f"{tier}_comm_p50_ms"] is not None and not r.get("cpu_bound")]
            busy = [(r["robots"], r[f"{tier}_comm_p50_ms"]) for r in rows
                    if r[f"{tier}_comm_p50_ms"] is not None and r.get("cpu_bound")]
            c1.points([p[0] for p in pts], [p[1] for p in pts], colour, f"{tier.upper()} (ours)", 5)
            if busy:
                c1.points([p[0] for p in busy], [p[1] for p in busy], colour,
                          f"{tier.upper()}, host CPU-bound (not fitted)", 5, "x")
            ch = out[f"{tier}_fit"]
            best = ch["fits"].get(ch["chosen"]) if ch.get("chosen") else None
            if best and pts:
                gx = np.linspace(min(p[0] for p in pts), max(p[0] for p in pts), 40)
                c1.line(gx, fitting.predict(best, gx), colour, f"{tier.upper()} fit: {best['formula']}", 1, True)
        c2 = Chart("Communication delay vs frame size (cloud, all runs)", "bytes sent", "ms", width=560)
        c2.points(xs, ys, BLUE, "ours", 2)
        if size_fit is not None and xs:
            gx = np.linspace(min(xs), max(xs), 20)
            c2.line(gx, fitting.predict(size_fit, gx), RED, f"fit a + b x, R2 {size_fit['r2']:.2f}")
        return hstack([c1.render(), c2.render()])
