"""What the thesis experiments share: a run's raw data, helpers, frames and visual checks (pure reading).

Split out of :mod:`scmr_mesh.thesis.analysis`; each experiment is a module of its own
(``exp1_4``, ``exp2``, ``exp3``, ``exp5``, ``exp6``, ``exp7``, ``table44``, ``model_checks``).
"""

from __future__ import annotations

import json
import logging
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from scmr_mesh.energy import Profile
from scmr_mesh.thesis.cpu import cpu_between, peer_series
from scmr_mesh.thesis.facts import Fact

log = logging.getLogger(__name__)

#: Pipeline mode the fleet runs serve (the robots' default).
SERVED_MODE = "best"
#: A region "is drivable" in the report when at least this share of its pixels is.
MOSTLY = 0.5
#: The four rows of thesis Figures 4.15 and 4.19.
ROWS = ("original", "SRM", "Otsu", "red/green")
#: A fleet run whose own processes used more than this share of the host's CPU time measures
#: CPU contention on the host, not the communication scheme (Table 4.4 fits leave it out).
CPU_BOUND = 0.5


# ----------------------------------------------------------------------------- raw data
@dataclass
class Run:
    """One fleet run's raw data."""

    name: str
    dir: Path
    info: dict[str, Any]
    records: list[dict[str, Any]]
    cpu: dict[str, Any]

    @property
    def t0(self) -> int:
        return int(self.info["t0_unix_ns"])

    @property
    def end(self) -> int:
        return self.t0 + int(float(self.info["scenario"]["duration_s"]) * 1e9)

    def robots(self) -> list[str]:
        return [r["id"] for r in self.info["scenario"]["fleet"]["robots"]]

    def profile(self, robot: str) -> str:
        return next(r["profile"] for r in self.info["scenario"]["fleet"]["robots"] if r["id"] == robot)

    def fault(self, kind: str, index: int = 0) -> dict[str, Any] | None:
        fs = [f for f in self.info["faults"] if f["kind"] == kind]
        return fs[index] if len(fs) > index else None

    def cpu_s(self, peer: str, a_ns: float, b_ns: float) -> float | None:
        return cpu_between(peer_series(self.cpu, peer), a_ns, b_ns)

    def rel(self, path: Path) -> str:
        return str(Path("runs") / self.name / path)


def read_records(run_dir: Path) -> list[dict[str, Any]]:
    """The request records of the scenario run in ``run_dir`` (as the scenario runner reads them)."""
    from scmr_mesh.scenario.runner import read_run_records

    return read_run_records(run_dir / "robots")


def load_run(out: Path, name: str) -> Run | None:
    d = Path(out) / "runs" / name
    if not (d / "run.json").is_file():
        return None
    cpu = json.loads((d / "cpu.json").read_text()) if (d / "cpu.json").is_file() else {"series": {}}
    return Run(name, d, json.loads((d / "run.json").read_text()), read_records(d), cpu)


# ----------------------------------------------------------------------------- helpers
def _median(xs: Sequence[float]) -> float | None:
    xs = [float(x) for x in xs if x is not None]
    return float(statistics.median(xs)) if xs else None


def _r(x: float | None, nd: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def _g(x: float | None) -> str:
    """A number for a sentence: three significant digits, or '-'."""
    return "-" if x is None else f"{x:.3g}"


def _single(rec: dict[str, Any]) -> bool:
    """Answered at the first attempt (no failover inside the request)."""
    att = rec.get("attempts") or []
    return bool(rec.get("ok")) and len(att) == 1 and att[0].get("outcome") == "ok"


def comm_ms(rec: dict[str, Any]) -> float | None:
    """The part of the ToR not spent in the server: transfer, routing, the robot's own encode/decode."""
    if rec.get("server_ms") is None or rec.get("tor_ms") is None:
        return None
    return float(rec["tor_ms"]) - float(rec["server_ms"])


def in_window(rec: dict[str, Any], a_ns: float, b_ns: float) -> bool:
    t = rec.get("sent_unix_ns")
    return t is not None and a_ns <= int(t) < b_ns


def record_energy_j(rec: dict[str, Any], prof: Profile, up_Bps: float, down_Bps: float) -> float | None:
    """Robot energy of one answered request: Eq 4.3-4.4 with the measured wait and bytes, Eq 4.2 for local.

    Remote: ``P_i * ToR + P_u * bytes_up / B_u + P_d * bytes_down / B_d``; local: ``P_c * ToR``
    (the same model as the scenario reports).
    """
    if not rec.get("ok") or rec.get("tor_ms") is None:
        return None
    tor_s = float(rec["tor_ms"]) / 1e3
    if rec.get("tier") == "local":
        return prof.p_compute_w * tor_s
    return (prof.p_idle_w * tor_s + prof.p_up_w * float(rec.get("bytes_up") or 0) / up_Bps
            + prof.p_down_w * float(rec.get("bytes_down") or 0) / down_Bps)


def server_energy(cpu_s: float, window_s: float, prof: Profile, idle_cpu_per_s: float = 0.0) -> dict[str, float]:
    """A server's energy over a window from its measured CPU time (linear power model).

    ``E = P_i * W + (P_c - P_i) * cpu``: idle power all the time, plus the computing increment
    for each CPU second.  ``serving_*`` is the increment for the CPU time above the server's own
    idle rate ``idle_cpu_per_s`` (measured while it served nobody): what serving the robots cost.
    """
    serving_cpu = max(0.0, cpu_s - idle_cpu_per_s * window_s)
    inc = prof.p_compute_w - prof.p_idle_w
    return {"cpu_s": cpu_s, "window_s": window_s, "util": cpu_s / window_s if window_s > 0 else 0.0,
            "idle_cpu_per_s": idle_cpu_per_s, "serving_cpu_s": serving_cpu,
            "energy_j": prof.p_idle_w * window_s + inc * cpu_s,
            "serving_j": inc * serving_cpu,
            "serving_w": inc * serving_cpu / window_s if window_s > 0 else 0.0}


def _claim(f: Fact, **extra: Any) -> dict[str, Any]:
    return f.claim(**extra)


def _check(fact: Fact, ours: dict[str, Any], holds: Any, why: str) -> dict[str, Any]:
    return {"claim": _claim(fact), "ours": ours, "holds": holds, "why": why}


# ----------------------------------------------------------------------------- frames and stages
class Frames:
    """The frames each robot of a run sent, with the pipeline's stage images for each (cached)."""

    def __init__(self, run: Run, manifest: dict[str, Any] | None) -> None:
        self.run = run
        self.manifest = manifest or {}
        self._frames: dict[tuple[str, str], Any] = {}
        self._stages: dict[tuple[str, str, str], Any] = {}

    def names(self, robot: str) -> list[str]:
        d = self.run.dir / "images" / robot
        return sorted(p.name for p in d.iterdir()) if d.is_dir() else []

    def frame(self, robot: str, name: str):
        key = (robot, name)
        if key not in self._frames:
            from scmr_mesh.mesh.robot import image_frames

            d = self.run.dir / "images" / robot
            gen = image_frames(d)  # the robot's own encoding of each file (JPEG q90 for PNGs)
            for _ in self.names(robot):
                fr = next(gen)
                self._frames[(robot, fr.name)] = fr
        return self._frames.get(key)

    def source(self, robot: str, name: str) -> Path:
        return (self.run.dir / "images" / robot / name).resolve()

    def stages(self, robot: str, name: str, mode: str):
        key = (robot, name, mode)
        if key not in self._stages:
            from scmr_mesh.imaging import decode_frame, segment_drivable

            fr = self.frame(robot, name)
            rgb = decode_frame(fr.data)
            self._stages[key] = segment_drivable(rgb, mode=mode, stages=True)
        return self._stages[key]

    def truth(self, robot: str, name: str):
        item = self.manifest.get(str(self.source(robot, name)))
        if item is None:
            return None
        from scmr_mesh.imaging.evaluate import truth_at_frame

        return truth_at_frame(item)


def _mask(run: Run, rec: dict[str, Any]):
    import cv2

    p = run.dir / "robots" / str(rec["robot"]) / "inbox" / f"{rec['seq']}.mask.png"
    if not p.is_file():
        return None
    return cv2.imdecode(np.frombuffer(p.read_bytes(), np.uint8), cv2.IMREAD_GRAYSCALE)


def bottom_centre_share(mask: np.ndarray) -> float:
    """Share of drivable pixels in the bottom-centre cell (the region closest to the robot, thesis 3.2)."""
    from scmr_mesh.imaging import bottom_centre, roi

    cell = bottom_centre(roi(mask))
    return float(np.count_nonzero(cell == 255)) / cell.size


def _manifest(data_dir: Path | None) -> dict[str, Any]:
    if data_dir is None or not (Path(data_dir) / "manifest.json").is_file():
        return {}
    from scmr_mesh.imaging.evaluate import load_manifest

    return {str(Path(it.image).resolve()): it for it in load_manifest(data_dir)}


def visual(run: Run, frames: Frames, tier: str, window: tuple[int, int] | None, reference: dict | None,
           ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per robot and image: the served mask of ``tier`` against the frame's stages here.

    Returns ``(rows, columns)``: report rows, and figure columns (the four rows of pictures).
    """
    from scmr_mesh.imaging.evaluate import score
    from scmr_mesh.imaging.steps import red_green

    rows, columns = [], []
    for robot in run.robots():
        for name in frames.names(robot):
            recs = [r for r in run.records if r.get("robot") == robot and r.get("image") == name and r.get("ok")
                    and r.get("tier") == tier and (window is None or in_window(r, *window))]
            masks = [m for m in (_mask(run, r) for r in recs) if m is not None]
            st = frames.stages(robot, name, SERVED_MODE)
            th = frames.stages(robot, name, "thesis")
            served = masks[0] if masks else None
            row: dict[str, Any] = {
                "robot": robot, "image": name, "bytes": len(frames.frame(robot, name).data),
                "answers": len(recs), "masks": len(masks),
                "answers_agree": bool(masks) and all(np.array_equal(m, masks[0]) for m in masks),
                "same_as_here": None if served is None else bool(np.array_equal(served, st.mask)),
                "bottom_centre_drivable": None if served is None else _r(bottom_centre_share(served)),
                "thesis_mode_bottom_centre_drivable": _r(bottom_centre_share(th.mask)),
            }
            if reference is not None:
                ref = reference.get((robot, name))
                row["same_as_cloud"] = None if served is None or ref is None else bool(np.array_equal(served, ref))
            truth = frames.truth(robot, name)
            if truth is not None and served is not None:
                row["iou"] = _r(score(served, truth[0], truth[1])["iou"])
                row["thesis_mode_iou"] = _r(score(th.mask, truth[0], truth[1])["iou"])
            rows.append(row)
            columns.append({"robot": robot, "image": name, "served": served, "stages": st, "thesis": th,
                            "label": f"{robot} {name[3:]}\n{len(recs)} {tier} answers"
                                     + ("" if served is None else f", bottom {row['bottom_centre_drivable']:.2f}"),
                            "red_green": None if served is None else red_green(served)})
    return rows, columns


def _visual_figures(columns: list[dict], tier_label: str, prefix: str, figdir: Path | None) -> list[str]:
    if figdir is None:
        return []
    from scmr_mesh.imaging.steps import red_green
    from scmr_mesh.thesis.figures import image_grid, write_png

    out = []
    for robot in sorted({c["robot"] for c in columns}):
        cols = [{"label": c["label"], "rows": [c["stages"].stages["frame"], c["stages"].stages["srm"],
                                              c["stages"].stages["otsu"], c["red_green"]]}
                for c in columns if c["robot"] == robot]
        img = image_grid(cols, ROWS, title=f"{robot}: {tier_label} (mode {SERVED_MODE}; rows 2-3 computed here "
                                           "from the frame the robot sent, row 4 the mask as served)")
        out.append(str(write_png(img, figdir / f"{prefix}_{robot}.png").relative_to(figdir.parent)))
    cols = [{"label": f"{c['robot']} {c['image'][3:]}",
             "rows": [c["thesis"].stages["frame"], c["thesis"].stages["srm"], c["thesis"].stages["otsu"],
                      red_green(c["thesis"].mask)]} for c in columns]
    img = image_grid(cols, ROWS, title="the literal dissertation rules (mode thesis, SRM Q = 32), computed here "
                                       "on the same frames", cell_w=160)
    out.append(str(write_png(img, figdir / f"{prefix}_thesis_mode.png").relative_to(figdir.parent)))
    return out


# ----------------------------------------------------------------------------- experiments
