"""Experiment 7: the energy model's placement sweep.

A mixin of :class:`scmr_mesh.thesis.analysis.Builder` (``self``: the builder with its runs).
"""

from __future__ import annotations

import logging
from typing import Any

from scmr_mesh.energy import PROFILES
from scmr_mesh.energy.model import MIB, THESIS_MBPS, break_even_up_Bps
from scmr_mesh.thesis.common import _check, _claim, _g, _median, _r

log = logging.getLogger(__name__)


class Exp7Mixin:
    """Experiment 7: the energy model's placement sweep."""

    def exp7(self) -> dict[str, Any]:
        from scmr_mesh.energy.experiments import sweep

        f = self.facts
        be = f["exp7_break_even"].values
        d1, d2 = int(be["size1_mb"] * MIB), int(be["size2_mb"] * MIB)
        cycles = float(f["eq49"].values["c"]) * 1e9
        bws = [float(b) * THESIS_MBPS for b in range(1, 101)]
        profs = [PROFILES[p] for p in ("leader", "robot1", "robot2", "robot3", "robot4")]
        res = sweep(profs, sizes_bytes=[d1, d2], bandwidths_Bps=bws, cycles=cycles)
        table = {p["profile"]: {f"{b['size_bytes'] / MIB:g}MB": _r(b["closed_form_mbps"], 2) for b in p["break_even"]}
                 for p in res["profiles"]}
        tol = 0.2

        def near(v: float, want: float) -> bool:
            return abs(v - want) <= tol * want

        k1, k2 = f"{be['size1_mb']:g}MB", f"{be['size2_mb']:g}MB"
        matching = [p for p, t in table.items() if near(t[k1], be["bw1_mbps"]) and near(t[k2], be["bw2_mbps"])]
        mc = self.measured_cycles()
        run = self.run("noloss")
        ups = [int(r["bytes_up"]) for r in run.records if r.get("ok") and r.get("tier") == "cloud"]
        downs = [int(r["bytes_down"]) for r in run.records if r.get("ok") and r.get("tier") == "cloud"]
        measured = {}
        if mc["cycles"] and ups:
            ratio = float(f["eq49_bytes"].values["b_d_Bps"]) / float(f["eq49_bytes"].values["b_u_Bps"])
            for p in profs:
                measured[p.name] = _r(break_even_up_Bps(p, cycles=mc["cycles"], bytes_up=_median(ups),
                                                         bytes_down=_median(downs), down_up_ratio=ratio)
                                      / THESIS_MBPS, 2)
        lead_lower = table["leader"][k1] < table["robot1"][k1]
        return {
            "title": "Optimal task execution policy (break-even bandwidth)",
            "claim": _claim(f["exp7_break_even"]),
            "ours": {"break_even_mbps": table, "within_pct": int(tol * 100), "profiles_matching": matching,
                     "measured_inputs": {"cycles": mc["cycles"], "frame_bytes_p50": _median(ups),
                                         "reply_bytes_p50": _median(downs), "break_even_mbps": measured}},
            "holds": bool(matching),
            "why": (("holds for " + ", ".join(matching) + " only" if matching else "holds for no Table 4.3 profile")
                    + f" (break-even within {tol:.0%} of {be['bw1_mbps']:g} and {be['bw2_mbps']:g} Mb/s): "
                    + "; ".join(f"{p} {t[k1]} / {t[k2]} Mb/s" for p, t in table.items())
                    + ". The break-even is proportional to the image size (the thesis's 70/25 = 2.8 is close to the "
                      "exact 3). With the CPU time and frames measured here (C = "
                    + f"{_g(mc['cycles'])} cycles, {_g(_median(ups))} B up) offloading saves robot energy only above "
                    + ", ".join(f"{p} {v}" for p, v in measured.items()) + " Mb/s."),
            "checks": [_check(f["exp7_leader_lower"], {"leader_1MB_mbps": table["leader"][k1],
                                                      "robot1_1MB_mbps": table["robot1"][k1]}, lead_lower,
                              "the reverse holds under the thesis's own equations: the leader breaks even at "
                              f"{table['leader'][k1]} Mb/s and robot1 at {table['robot1'][k1]} Mb/s for 1 MB (a fast "
                              "robot computes the task cheaply itself, so a faster link is needed before shipping it "
                              "pays)")],
            "figures": self.fig(lambda: self._fig_sweep(res, be), "exp7_sweep.png"),
            "inputs": {"measured": self.measured(run) + ["runs/noloss/cpu.json"],
                       "cited": ["exp7_break_even", "exp7_leader_lower", "eq49", "eq49_bytes", "f300", "table43"],
                       "assumed": {"bandwidth_grid": {"value": "1..100 Mb/s, B_d / B_u as Eq 4.9",
                                                      "why": "the range of Figure 4.22"}}},
        }

    # -- model pieces ---------------------------------------------------------

    def _fig_sweep(self, res, be):
        from scmr_mesh.thesis.figures import BLUE, ORANGE, RED, Chart, hstack, vstack

        charts = []
        for p in res["profiles"]:
            top = max(x["e_saved_j"] for x in p["grid"])
            lim = (-1.5 * top, 1.15 * top) if top > 0 else None  # deep losses at low bandwidth clipped
            c = Chart(f"{p['profile']}: E_saved vs bandwidth", "Mb/s (upload)", "J saved by offloading (losses clipped)",
                      width=420, height=300, ylim=lim)
            for size, colour in zip(res["params"]["sizes_bytes"], (BLUE, ORANGE)):
                g = [x for x in p["grid"] if x["size_bytes"] == size]
                c.line([x["bandwidth_mbps"] for x in g], [x["e_saved_j"] for x in g], colour, f"{size / MIB:g} MB")
            for b in p["break_even"]:
                c.points([b["closed_form_mbps"]], [0.0], BLUE if b["size_bytes"] == res["params"]["sizes_bytes"][0]
                         else ORANGE, None, 6, "x")
            c.hline(0.0)
            c.vline(be["bw1_mbps"], RED, "thesis: 1 MB saves from ~25, 3 MB from ~70 Mb/s", "25")
            c.vline(be["bw2_mbps"], RED, None, "70")
            charts.append(c.render())
        rows = [hstack(charts[i:i + 3]) for i in range(0, len(charts), 3)]
        return vstack(rows)
