"""Experiment 3: robots' energy by fleet size and where the frames ran.

A mixin of :class:`scmr_mesh.thesis.analysis.Builder` (``self``: the builder with its runs).
"""

from __future__ import annotations

import logging
import statistics
from typing import Any

from scmr_mesh.energy import PROFILES
from scmr_mesh.energy.model import THESIS_MBPS
from scmr_mesh.thesis import fit as fitting
from scmr_mesh.thesis.common import _check, _claim, _r, in_window, server_energy

log = logging.getLogger(__name__)


class Exp3Mixin:
    """Experiment 3: robots' energy by fleet size and where the frames ran."""

    def cloud_vs_n(self) -> list[dict[str, Any]]:
        """Per fleet size: the cloud's measured CPU in the R2C half, and its energy (Figure 4.17 D)."""
        rows = []
        for n, run in self.size_runs():
            cut = self._cut(run)
            cpu = run.cpu_s("cloud", run.t0, cut)
            frames = sum(1 for r in run.records if r.get("ok") and r.get("tier") == "cloud" and in_window(r, run.t0, cut))
            # the cloud's idle rate: its CPU once it was cut from everyone (it serves nobody then)
            settle, heal = cut + int(0.5e9), self._heal(run)
            idle = run.cpu_s("cloud", settle, heal) if heal > settle else None
            if cpu is None:
                continue
            e = server_energy(cpu, (cut - run.t0) / 1e9, self.leader_prof,
                              idle / ((heal - settle) / 1e9) if idle is not None else 0.0)
            rows.append({"robots": n, "frames": frames, **{k: _r(v, 4) for k, v in e.items()},
                         "serving_j_per_frame": _r(e["serving_j"] / frames, 4) if frames else None})
        return rows


    def exp3(self) -> dict[str, Any]:
        f = self.facts
        run = self.run("noloss")
        cloud = [r for r in run.records if r.get("ok") and r.get("tier") == "cloud"]
        same_frames = {p: _r(statistics.mean(self._robot_energy(run, cloud, p)), 4) for p in
                       ("robot1", "robot2", "robot3", "robot4", "leader")} if cloud else {}
        order = sorted(same_frames, key=lambda p: PROFILES[p].p_compute_w)
        monotone = all(same_frames[a] < same_frames[b] for a, b in zip(order, order[1:])) if same_frames else None
        own = {}
        for rid in run.robots():
            es = self._robot_energy(run, [r for r in cloud if r["robot"] == rid])
            own[rid] = {"profile": run.profile(rid), "requests": len(es), "mean_j": _r(statistics.mean(es), 4) if es else None,
                        "total_j": _r(sum(es), 3)}
        # Figure 4.17 (B): E_cloud from 25 to 70 Mb/s (Eq 4.9 inputs)
        bw = f["exp3_bandwidth"].values
        d = float(f["eq49_bytes"].values["d_bytes"])
        ratio = float(f["eq49_bytes"].values["b_d_Bps"]) / float(f["eq49_bytes"].values["b_u_Bps"])
        cycles = float(f["eq49"].values["c"]) * 1e9
        from scmr_mesh.energy import LinkEstimate, Task, energy_terms

        red = {}
        for p in ("leader", "robot1", "robot2", "robot3", "robot4"):
            e = [energy_terms(Task(cycles, d, d), PROFILES[p],
                              LinkEstimate(b * THESIS_MBPS, ratio * b * THESIS_MBPS))["e_cloud_j"]
                 for b in (bw["from_mbps"], bw["to_mbps"])]
            red[p] = _r(100.0 * (1 - e[1] / e[0]), 2)
        mean_red = _r(statistics.mean(red.values()), 2)
        servers = self.cloud_vs_n()
        ch = fitting.choose([s["robots"] for s in servers], [s["serving_w"] for s in servers], ("const", "linear", "exp")) \
            if len(servers) >= 3 else {"chosen": None, "fits": {}}
        # exponential in the robots means growth faster than any power; a growth order b of y = a N^b
        # significantly above 1 is the least it needs
        growth = fitting.growth_order([s["robots"] for s in servers], [s["serving_w"] for s in servers])
        superlinear = bool(growth and growth["superlinear"])
        exp_holds = superlinear if growth is not None else \
            "not comparable: fewer than three fleet sizes with cloud answers"
        return {
            "title": "Energy utilisation with no cloud disconnection",
            "claim": _claim(f["exp3_profiles"]),
            "ours": {"energy_per_request_same_frames_j": same_frames, "order_by_p_compute": order,
                     "p_compute_w": {p: PROFILES[p].p_compute_w for p in order},
                     "per_robot_own_frames": own,
                     "model": "robot energy of a cloud answer = P_i x ToR + P_u x bytes_up / B_u + P_d x bytes_down / "
                              "B_d (Eq 4.3-4.4 with the measured wait and bytes; B_u, B_d of Eq 4.9)"},
            "holds": monotone,
            "why": (f"on the same {len(cloud)} measured cloud answers, the robot energy per request rises with the "
                    f"profile's computing power ({', '.join(f'{p} {same_frames[p]} J' for p in order)}). It follows "
                    "from Table 4.3 itself: P_u and P_d are 1.78 and 2.21 x P_c for every robot, and the transfer "
                    "terms dominate."),
            "checks": [
                _check(f["exp3_bandwidth"], {"reduction_pct_by_profile": red, "mean_reduction_pct": mean_red},
                       abs(mean_red - bw["reduction_pct"]) <= 5.0,
                       f"Eq 4.9 with 1 MB at {bw['from_mbps']:g} and {bw['to_mbps']:g} Mb/s (B_d / B_u as Eq 4.9) "
                       f"lowers E_cloud by {mean_red} % on average, not {bw['reduction_pct']:g} %: E_trans is "
                       "proportional to 1/B and the idle term is under 1 %, so the thesis's own equations give "
                       "1 - 25/70 = 64 %"),
                _check(f["exp3_servers"], {"cloud_vs_robots": servers, "fit": ch, "growth_order": growth},
                       exp_holds,
                       "the cloud's serving power (measured CPU time above its idle rate) against the fleet size: "
                       + ", ".join(f"{s['robots']} robots {s['serving_w']} W" for s in servers)
                       + ("" if growth is None else
                          f"; growth order {growth['b']:.2f} +- {growth['b_se']:.2f} (y = a N^b)")
                       + f" (leave-one-out among constant, linear, exponential: {ch['chosen']}); per frame "
                       + ", ".join(f"{s['serving_j_per_frame']} J" for s in servers) + ": "
                       + ("the energy grows faster than linearly with the robots" if superlinear else
                          "the energy grows about linearly with the robots (each frame costs about the same), "
                          "not exponentially")),
            ],
            "figures": self.fig(lambda: self._fig_energy3(same_frames, order, servers, ch), "exp3_energy.png"),
            "inputs": {"measured": self.measured(run) + [f"runs/{r.name}/cpu.json" for _, r in self.size_runs()],
                       "cited": ["exp3_profiles", "exp3_bandwidth", "exp3_servers", "eq49", "eq49_bytes", "table43"],
                       "assumed": self.assumed()},
        }


    def _fig_energy3(self, same, order, servers, ch):
        import numpy as np

        from scmr_mesh.thesis.figures import BLUE, RED, Chart, hstack

        c1 = Chart("Robot energy per cloud answer, same frames (Fig 4.17 A/C)", "P_compute of the profile (W)",
                   "J per request", width=560)
        c1.points([PROFILES[p].p_compute_w for p in order], [same[p] for p in order], BLUE, "ours (measured waits)", 5)
        c1.line([PROFILES[p].p_compute_w for p in order], [same[p] for p in order], BLUE)
        c2 = Chart("Cloud serving power vs robots (Fig 4.17 D)", "robots", "W (measured CPU)", width=560)
        if servers:
            c2.points([s["robots"] for s in servers], [s["serving_w"] for s in servers], BLUE, "ours", 5)
            best = ch["fits"].get(ch["chosen"]) if ch.get("chosen") else None
            if best:
                gx = np.linspace(min(s["robots"] for s in servers), max(s["robots"] for s in servers), 30)
                c2.line(gx, fitting.predict(best, gx), RED, f"chosen fit: {best['formula']}")
        return hstack([c1.render(), c2.render()])
