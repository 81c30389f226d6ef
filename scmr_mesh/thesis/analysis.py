"""The thesis report, built from the raw data of a ``scmr thesis`` run (runs no peer).

:func:`build` reads ``OUT/thesis_run.json`` (configuration, host, load), and for each fleet
run ``OUT/runs/<name>/`` (``run.json``, ``cpu.json``, the robots' records and masks, the
links to the frames they sent), computes experiments 1-7 and the model checks (Eq 3.14,
Eq 3.18-3.19, Table 4.4), and, with ``draw=True``, writes the figures into ``OUT/figures/``.
Every number of a claim comes from :mod:`scmr_mesh.thesis.facts` (the dissertation's
published figures); every number of ours from those raw files; the model's assumed inputs
are listed with the reason under each experiment's ``inputs.assumed``.  Building twice from
the same files gives the same report (tests/test_thesis.py checks it).

Pipeline mode: every fleet run serves ``best`` (the robots' default: the self-supervised road
model, docs/ACCURACY.md); experiments 1 and 4 also show the literal dissertation rules
(``thesis`` mode) computed here on the same frames, for comparison.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable, Sequence

from scmr_mesh.energy import PROFILES
from scmr_mesh.thesis.facts import load_facts, table_4_2_for

log = logging.getLogger(__name__)
from scmr_mesh.thesis.exp1_4 import Exp14Mixin
from scmr_mesh.thesis.exp2 import Exp2Mixin
from scmr_mesh.thesis.exp5 import Exp5Mixin
from scmr_mesh.thesis.exp3 import Exp3Mixin
from scmr_mesh.thesis.exp6 import Exp6Mixin
from scmr_mesh.thesis.exp7 import Exp7Mixin
from scmr_mesh.thesis.table44 import Table44Mixin
from scmr_mesh.thesis.model_checks import ModelChecksMixin
from scmr_mesh.thesis.common import Run, SERVED_MODE, _manifest, _median, _r, _single, comm_ms, in_window, load_run, record_energy_j


class Builder(Exp14Mixin, Exp2Mixin, Exp5Mixin, Exp3Mixin, Exp6Mixin, Exp7Mixin, Table44Mixin, ModelChecksMixin):
    """Computes the report from the raw data (one instance per build)."""

    def __init__(self, out: Path, *, draw: bool = True) -> None:
        self.out = Path(out)
        self.meta = json.loads((self.out / "thesis_run.json").read_text())
        self.facts = load_facts()
        self.runs = {n: load_run(self.out, n) for n in self.meta["runs"]}
        self.figdir = self.out / "figures" if draw else None
        if self.figdir is not None:
            self.figdir.mkdir(parents=True, exist_ok=True)
        data = self.meta.get("data_dir")
        self.manifest = _manifest(Path(data)) if data else {}
        self.leader_prof = PROFILES["leader"]
        f = self.facts
        self.up_Bps = float(f["eq49_bytes"].values["b_u_Bps"])
        self.down_Bps = float(f["eq49_bytes"].values["b_d_Bps"])
        self.host_hz = float(self.meta["host"]["clock_hz"])
        self.cpus = int(self.meta["host"].get("cpus") or 1)

    # -- plumbing ------------------------------------------------------------
    def run(self, name: str) -> Run:
        r = self.runs.get(name)
        if r is None:
            raise FileNotFoundError(f"run {name} missing in {self.out / 'runs'}")
        return r

    def measured(self, *runs: Run, what: str = "records.jsonl, masks") -> list[str]:
        return [f"runs/{r.name}/ ({what})" for r in runs]

    def fig(self, draw: Callable[[], Any], name: str) -> list[str]:
        if self.figdir is None:
            return []
        from scmr_mesh.thesis.figures import write_png

        img = draw()
        return [str(write_png(img, self.figdir / name).relative_to(self.out))]

    def assumed(self) -> dict[str, Any]:
        return {
            "server_powers": {"value": {"p_compute_w": self.leader_prof.p_compute_w,
                                        "p_idle_w": self.leader_prof.p_idle_w},
                              "why": "the thesis gives no cloud server's power: both servers (they run on this host) "
                                     "are costed with Table 4.3's leader machine (i7-3770), so they differ only by "
                                     "measured CPU time"},
            "server_power_model": {"value": "E = P_i * W + (P_c - P_i) * cpu_s",
                                   "why": "linear power model: idle power over the window plus the computing "
                                          "increment per measured CPU second"},
        }

    # -- experiments 1 and 4 -------------------------------------------------

    def _per_image_tor(self, run: Run, tier: str, window=None) -> dict[tuple[str, str], dict[str, Any]]:
        out: dict[tuple[str, str], dict[str, Any]] = {}
        for rec in run.records:
            if not rec.get("ok") or rec.get("tier") != tier or (window and not in_window(rec, *window)):
                continue
            d = out.setdefault((rec["robot"], rec["image"]), {"tor": [], "server": [], "comm": [], "bytes": []})
            d["tor"].append(float(rec["tor_ms"]))
            d["server"].append(float(rec.get("server_ms") or 0.0))
            if _single(rec) and comm_ms(rec) is not None:
                d["comm"].append(comm_ms(rec))
            d["bytes"].append(int(rec.get("bytes_up") or 0))
        return {k: {"n": len(v["tor"]), "tor_p50_ms": _r(_median(v["tor"])), "server_p50_ms": _r(_median(v["server"])),
                    "comm_p50_ms": _r(_median(v["comm"])), "bytes": int(_median(v["bytes"]) or 0)}
                for k, v in out.items()}

    def table_4_2_side_by_side(self, run: Run, ours_cloud: dict, ours_leader: dict | None) -> list[dict[str, Any]]:
        rows = []
        for robot in run.robots():
            thesis_rows = table_4_2_for(robot)
            for i, name in enumerate(sorted({r["image"] for r in run.records if r.get("robot") == robot})):
                t = thesis_rows[i] if i < len(thesis_rows) else None
                c = ours_cloud.get((robot, name), {})
                lead = (ours_leader or {}).get((robot, name), {})
                rows.append({
                    "robot": robot, "image": name, "bytes": c.get("bytes") or lead.get("bytes"),
                    "cloud_n": c.get("n", 0), "cloud_tor_p50_ms": c.get("tor_p50_ms"),
                    "server_p50_ms": c.get("server_p50_ms"), "comm_p50_ms": c.get("comm_p50_ms"),
                    "leader_n": lead.get("n", 0), "leader_tor_p50_ms": lead.get("tor_p50_ms"),
                    "leader_server_p50_ms": lead.get("server_p50_ms"),
                    "thesis_image": t["image"] if t else None, "thesis_description": t["description"] if t else None,
                    "thesis_bytes": t["original_bytes"] if t else None,
                    "thesis_cloud_tor_ms": t["cloud_tor_ms"] if t else None,
                    "thesis_r2c_processing_ms": t["r2c_processing_ms"] if t else None,
                    "thesis_r2r_leader_ms": t["r2r_leader_processing_ms"] if t else None,
                })
        return rows


    def _robot_energy(self, run: Run, recs: Sequence[dict], profile: str | None = None) -> list[float]:
        out = []
        for r in recs:
            prof = PROFILES[profile or run.profile(r["robot"])]
            e = record_energy_j(r, prof, self.up_Bps, self.down_Bps)
            if e is not None:
                out.append(e)
        return out

    def size_runs(self) -> list[tuple[int, Run]]:
        out = []
        for name in self.meta["runs"]:
            if name.startswith("size"):
                out.append((int(name[4:]), self.run(name)))
        return sorted(out)

    def _cut(self, run: Run) -> int:
        p = run.fault("partition")
        return int(p["start_unix_ns"]) if p else run.end

    def _heal(self, run: Run) -> int:
        """When the cloud came back (the run's end if it never did)."""
        p = run.fault("partition")
        return int(p["end_unix_ns"]) if p and p.get("end_unix_ns") else run.end


    def measured_cycles(self) -> dict[str, Any]:
        run = self.run("noloss")
        cpu = run.cpu_s("cloud", run.t0, run.end)
        frames = sum(1 for r in run.records if r.get("ok") and r.get("tier") == "cloud" and in_window(r, run.t0, run.end))
        if not cpu or not frames:
            return {"cpu_s_per_frame": None, "cycles": None}
        return {"cpu_s_per_frame": _r(cpu / frames, 5), "cycles": _r(cpu / frames * self.host_hz, 0),
                "host_hz": self.host_hz, "frames": frames,
                "how": "the cloud's CPU seconds over the no-loss run / frames it answered (includes its own "
                       "overhead: zenoh, load messages) x this host's clock"}


def build(out: Path, *, draw: bool = True, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The report (a JSON-able dict) from the raw data in ``out``; figures into ``out/figures`` when ``draw``."""
    say = progress or (lambda m: None)
    b = Builder(out, draw=draw)
    say("experiments 1 and 4: stage images of every frame")
    e1, e4 = b.exp1_4()
    say("experiments 2, 3, 5, 6, 7")
    exps = {"1": e1, "2": b.exp2(), "3": b.exp3(), "4": e4, "5": b.exp5(), "6": b.exp6(), "7": b.exp7()}
    say("model pieces: Table 4.4, Eq 3.14, Eq 3.18-3.19")
    model = {"table_4_4": b.table_4_4(), "eq_3_14": b.eq_3_14(), "eq_3_18_19": b.eq_3_18_19()}
    runs = {}
    for name, r in b.runs.items():
        if r is None:
            continue
        ok = sum(bool(x.get("ok")) for x in r.records)
        runs[name] = {"scenario": r.info["scenario"]["name"], "backend": r.info["backend"],
                      "duration_s": r.info["scenario"]["duration_s"], "robots": len(r.robots()),
                      "requests": len(r.records), "ror": _r(ok / len(r.records)) if r.records else None,
                      "wall_s": r.info.get("wall_s"), "notes": r.info.get("notes", []),
                      "telemetry_lost": (r.info.get("telemetry") or {}).get("lost"),
                      "faults": [x["label"] for x in r.info["faults"]]}
    cited = sorted({c for e in [*exps.values(), *model.values()] for c in e.get("inputs", {}).get("cited", [])})
    facts = load_facts()
    return {
        "v": 1, "kind": "thesis-report",
        "config": b.meta["config"], "host": b.meta["host"], "timing": b.meta.get("timing", {}),
        "served_mode": SERVED_MODE,
        "experiments": exps, "model": model, "runs": runs,
        "facts": {k: {"source": facts[k].source, "quote": facts[k].quote, "values": facts[k].values}
                  for k in cited if k in facts},
    }
