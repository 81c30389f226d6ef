"""Model checks: Eq 3.14 (utility ranking) and Eq 3.18-3.19.

A mixin of :class:`scmr_mesh.thesis.analysis.Builder` (``self``: the builder with its runs).
"""

from __future__ import annotations

import logging
import statistics
from typing import Any

import numpy as np

from scmr_mesh.energy import PROFILES
from scmr_mesh.thesis.common import _claim, _median, _r

log = logging.getLogger(__name__)


class ModelChecksMixin:
    """Model checks: Eq 3.14 (utility ranking) and Eq 3.18-3.19."""

    def eq_3_14(self) -> dict[str, Any]:
        from scmr_mesh.qos.negotiator import Negotiator, UtilityRanking

        run = self.run("noloss")
        recs = [r for r in run.records if r.get("ok") and r.get("tier") == "cloud" and r.get("server_ms") is not None]
        if len(recs) < 2:
            return {"title": "Eq 3.14 ranking", "claim": _claim(self.facts["eq314"]), "ours": None,
                    "why": "too few answers to replay"}
        ranking = UtilityRanking(w_time=1.0, w_expense=0.0)

        def replay(rank: UtilityRanking | None) -> float:
            n = Negotiator(capacity=len(recs), workers=1, ranking=rank)
            for r in recs:  # the service-time model learns the measured (size, service time) pairs
                n.service_model.observe(int(r["bytes_up"]), float(r["server_ms"]) / 1e3)
            for i, r in enumerate(recs):
                n.offer(i, 0, size=int(r["bytes_up"]))
            t, done = 0.0, []
            while True:
                e = n.take(timeout=0)
                if e is None:
                    break
                t += float(recs[e.request_id]["server_ms"])
                done.append(t)
                n.done(e)
            return statistics.mean(done)

        fifo, util = replay(None), replay(ranking)
        sz = np.array([float(r["bytes_up"]) for r in recs])
        sv = np.array([float(r["server_ms"]) for r in recs])
        corr = float(np.corrcoef(sz, sv)[0, 1]) if sz.std() > 0 and sv.std() > 0 else None
        return {
            "title": "Eq 3.14: utility ranking of the request negotiator",
            "claim": _claim(self.facts["eq314"]),
            "ours": {"requests": len(recs), "fifo_mean_completion_ms": _r(fifo, 2),
                     "utility_mean_completion_ms": _r(util, 2), "ratio": _r(util / fifo, 4),
                     "size_service_time_correlation": _r(corr),
                     "enable": "scmr cloud|leader --queue N --rank utility [--w-time W --w-expense W --price-cpu P "
                               "--price-mb P]"},
            "why": ("a replay of the no-loss run's cloud answers arriving at once at one worker (service time = the "
                    "measured server_ms; the ranking's service-time model learnt from the same answers): ranked by "
                    f"Eq 3.14 with w_e = 0 (shortest predicted job first) the mean completion time is {_r(util, 1)} ms "
                    f"against {_r(fifo, 1)} ms first come first served (ratio {_r(util / fifo, 3)}). The ranking can only "
                    "be as good as its prediction: the correlation of frame size and measured service time was "
                    f"{_r(corr)} here (frames are resized to 300x225 first, so only decoding depends on the size, and "
                    "a busy host adds noise); it shortens the queue when service time follows the size."),
            "inputs": {"measured": ["runs/noloss/ (records.jsonl: bytes_up, server_ms)"], "cited": ["eq314"],
                       "assumed": {"weights": {"value": {"w_time": 1.0, "w_expense": 0.0},
                                               "why": "one resource: with a CPU price only the expense is "
                                                      "proportional to the time and the ranking is the same"}}},
        }


    def eq_3_18_19(self) -> dict[str, Any]:
        import random

        from scmr_mesh.energy.transmission import (Channel, OptimalSchedule, equal_split_energy, lambda_from_eq44,
                                                   schedule_known_gains, simulate)

        f = self.facts
        run = self.run("noloss")
        ups = [int(r["bytes_up"]) for r in run.records if r.get("ok")]
        if not ups:
            return {"title": "Eq 3.18-3.19", "claim": _claim(f["eq318"]), "ours": None, "why": "no frame"}
        bits = 8.0 * float(_median(ups))
        prof = PROFILES["robot1"]
        up_Bps = float(f["eq49_bytes"].values["b_u_Bps"])
        n, slots, states, runs = 2.0, 10, 32, 2000
        e44 = lambda_from_eq44(prof.p_up_w, up_Bps) * bits  # Eq 4.4's upload energy of this frame (n = 1)
        lam = e44 / bits**n  # n = 2, calibrated: one slot at the mean gain costs what Eq 4.4 says
        ch = Channel.rayleigh(1.0, states=states)
        opt = OptimalSchedule(slots=slots, channel=ch, order=n)
        rng = random.Random(1)
        caus = clair = 0.0
        for _ in range(runs):
            g = [rng.choices(ch.gains, ch.probs)[0] for _ in range(slots)]
            caus += simulate(opt, bits, g, lam=lam)[1] / runs
            clair += schedule_known_gains(bits, g, lam=lam, order=n)[1] / runs
        eq = equal_split_energy(bits, slots, ch, lam=lam, order=n)
        ex = opt.expected_energy(bits, lam=lam)
        return {
            "title": "Eq 3.18-3.19: transmission energy and its optimal bit schedule",
            "claim": _claim(f["eq319"], also=_claim(f["eq318"])),
            "ours": {"frame_bits": bits, "eq44_one_slot_j": _r(e44, 4), "equal_split_j": _r(eq, 4),
                     "optimal_expected_j": _r(ex, 4), "optimal_simulated_j": _r(caus, 4),
                     "clairvoyant_j": _r(clair, 4), "saving_vs_equal_pct": _r(100 * (1 - ex / eq), 2)},
            "why": (f"the median frame ({bits / 8:.0f} B) sent by robot1 within {slots} slots over a Rayleigh-fading "
                    f"channel: spreading its bits evenly costs {_r(eq, 3)} J, the optimal causal schedule (Eq 3.19, "
                    f"dynamic programming) {_r(ex, 3)} J expected ({_r(caus, 3)} J in {runs} simulated channels), "
                    f"a robot that knew every future gain {_r(clair, 3)} J. With n = 1 and a channel that does not fade "
                    "(Eq 4.4's case) no schedule saves anything: energy is then linear in the bits."),
            "inputs": {"measured": ["runs/noloss/ (records.jsonl: bytes_up)"], "cited": ["eq318", "eq319",
                                                                                         "eq49_bytes", "table43"],
                       "assumed": {"order_n": {"value": n, "why": "the thesis gives no monomial order; 2 is the "
                                                                  "smallest that makes scheduling matter"},
                                   "slots": {"value": slots, "why": "the deadline in slots (not in the thesis)"},
                                   "channel": {"value": f"Rayleigh, mean gain 1, {states} equally likely states",
                                               "why": "the thesis names a stochastic fading channel, not its law"},
                                   "lambda": {"value": "one slot at the mean gain costs Eq 4.4's P_u * D / B_u",
                                              "why": "the thesis gives no energy coefficient"},
                                   "simulation": {"value": {"runs": runs, "seed": 1}, "why": "Monte Carlo check"}}},
        }

    # -- figures --------------------------------------------------------------
