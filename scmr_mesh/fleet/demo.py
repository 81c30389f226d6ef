"""``scmr demo``: the fleet demo on one host (what ``make demo`` runs).

A cloud, a dedicated leader and 4 robots (r1 and r2 leader-capable) on
loopback send built-in synthetic scenes
(:data:`scmr_mesh.imaging.synthetic.SCENE_KINDS`, one kind per robot) at 5 Hz
for 20 s; the cloud is SIGKILLed at 6 s and restarted at 10 s, and at 8 s,
while the cloud is out, whichever node leads is SIGKILLed too: a robot takes
the lead (docs/R2R.md).  The run goes on long enough to see the restarted
cloud answer again.  Nothing to
install or download.  At the end it prints the report table and where the
report, logs, masks and pictures are:

``OUT/report.json``, ``OUT/logs/``, ``OUT/robots/<id>/inbox/*.mask.png``,
``OUT/pictures/timeline.png`` (every request's ToR over time, coloured by the
tier that served it, outage shaded) and ``OUT/pictures/overlays.png`` (frames
with their red/green masks before, during and after the outage).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from scmr_mesh import cliargs as ca
from scmr_mesh.scenario.hooks import Hooks
from scmr_mesh.scenario.plots import TIER_COLOURS

__all__ = ["register", "render_overlays", "render_timeline"]

#: BGR colours of the serving tiers in the pictures (the reports' palette; None: failed).
TIER_BGR = {**{k: v for k, v in TIER_COLOURS.items() if k != "failed"}, None: TIER_COLOURS["failed"]}


def _outage(text: str) -> tuple[float, float]:
    from scmr_mesh.fleet.plan import parse_outage

    return parse_outage(text)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the fleet demo on one host (what `make demo` runs)",
        description=(
            "Run a cloud, a dedicated leader and 4 robots (the first two leader-capable) on loopback on "
            "built-in synthetic scenes, kill the cloud in the middle (SIGKILL at 6 s, restart at 10 s of a "
            "20 s run, leaving time for the restarted cloud to start up and answer again) and, while it is "
            "out, the node that leads (at 8 s: a robot takes the lead), and write the "
            "report, the peers' logs, every mask and two pictures (ToR timeline by tier, overlays "
            "before/during/after the outage).  Takes 30-50 s.  Exit 1 if a request or a "
            "telemetry record was lost, or a peer failed (the summary's PROBLEM lines)."
        ),
    )
    p.add_argument("--out", type=ca.PathArg("out-dir", as_path=True, example="runs/demo"), default=Path("runs/demo"),
                   help="run directory; a previous run there is replaced (default: %(default)s)")
    p.add_argument("--robots", type=ca.count("robots", hi=1000, example="4"), default=4, metavar="N", help="robots (default: %(default)s)")
    p.add_argument("--duration", type=ca.positive("seconds", hi=604800, example="20"), default=20.0, metavar="S", help="seconds (default: %(default)s)")
    p.add_argument("--rate", type=ca.positive("frames per second", hi=10000, example="5"), default=5.0, metavar="HZ", help="frames/s per robot (default: %(default)s)")
    p.add_argument("--cloud-outage", type=ca.parsed(_outage, what="START:END seconds with 0 <= START < END", example="6:10", positive=False, keep_text=True), default="6:10", metavar="START:END",
                   help="cloud SIGKILL and restart times in s (default: %(default)s)")
    p.add_argument("--leader-crash", type=ca.non_negative("seconds", hi=604800, example="8"), default=8.0, metavar="S",
                   help="SIGKILL whichever node leads at S s (default: %(default)s; another candidate takes "
                        "the lead)")
    p.add_argument("--no-leader-crash", action="store_true", help="do not crash the leader")
    p.add_argument("--quiet", action="store_true", help="no live progress")
    p.add_argument("--insecure", action="store_true",
                   help="run the peers without authentication (default: mutual TLS with certificates made in "
                        "OUT/certs, and the fleet's access rules)")
    from scmr_mesh.viz import add_rerun_args  # light: rerun is imported only when used

    add_rerun_args(p)
    p.add_argument("--no-rerun", action="store_true",
                   help="do not record the run for the rerun viewer (default: save OUT/demo.rrd)")
    p.set_defaults(func=run)


def _clear_previous(out: Path) -> None:
    """Remove a previous run in ``out`` (only folders marked by ``scmr up`` as run directories)."""
    from scmr_mesh.errors import InputError
    from scmr_mesh.fleet.plan import RUN_MARKER

    if not out.exists():
        return
    if not out.is_dir():
        raise InputError(f"--out must be a folder, got {out} (a file)")
    if (out / RUN_MARKER).is_file():
        shutil.rmtree(out)
    elif any(out.iterdir()):
        raise InputError(f"--out {out} is not empty and is not a previous run (no {RUN_MARKER} file); "
                         "choose a new or empty folder")


def run(args: argparse.Namespace) -> int:
    from scmr_mesh.errors import InputError
    from scmr_mesh.fleet.output import check_fleet, format_summary, run_with_output
    from scmr_mesh.fleet.plan import FleetConfig, parse_outage

    out = Path(args.out)
    _clear_previous(out)
    rerun = _rerun_options(args, out)
    crash = None if args.no_leader_crash else args.leader_crash
    if crash is not None and crash >= args.duration:
        raise InputError(f"--leader-crash {crash:g} is not before the end of the run (--duration {args.duration:g}); "
                         "give a time inside the run or --no-leader-crash")
    config = FleetConfig(robots=args.robots, duration_s=args.duration, rate_hz=args.rate,
                         cloud_outage=parse_outage(args.cloud_outage), run_dir=out, rerun=rerun,
                         leader_crash_s=crash, insecure=args.insecure)
    print(f"scmr demo: cloud, leader and {args.robots} robots on loopback"
          f"{' (INSECURE: no authentication)' if args.insecure else ', mutual TLS + access rules'} for {args.duration:g} s; "
          f"the cloud is killed at {config.cloud_outage[0]:g} s and restarted at {config.cloud_outage[1]:g} s"
          + (f"; the leader is killed at {crash:g} s" if crash is not None else ""), file=sys.stderr)
    pics = out / "pictures"
    report = run_with_output(config, quiet=args.quiet, hooks=(DemoPictures(pics),))
    print(format_summary(report))
    print(f"""
report:    {out / 'report.json'}
logs:      {out / 'logs'}/  (one per peer: cloud, leader, r1..r{args.robots})
masks:     {out / 'robots'}/<robot>/inbox/<seq>.mask.png  (255 = drivable); requests in records.jsonl
pictures:  {pics / 'timeline.png'}  (ToR per request over time, by serving tier)
           {pics / 'overlays.png'}  (frames with red/green masks before, during, after the outage)""")
    if rerun is not None and rerun.mode == "save":
        print(f"rerun:     {rerun.target}  (open it with `scmr view {rerun.target}`; "
              f"headless: `scmr view {rerun.target} --web`)")
    if report.get("interrupted"):
        return 130
    return check_fleet(report, 1.0)


class DemoPictures(Hooks):
    """The engine hook that draws the demo's pictures once the report is built."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)

    def reported(self, result: Any, report: Mapping[str, Any]) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        render_timeline(result.records, report, self.folder / "timeline.png")
        render_overlays(result.records, report, result.out_dir, self.folder / "overlays.png")


def _rerun_options(args: argparse.Namespace, out: Path):
    """The demo records OUT/demo.rrd unless another rerun flag or --no-rerun is given."""
    from scmr_mesh.errors import InputError
    from scmr_mesh.viz import RerunOptions

    opts = RerunOptions.from_args(args)
    if getattr(args, "no_rerun", False):
        if opts is not None:
            raise InputError("--no-rerun cannot be combined with --save/--spawn/--serve/--connect; drop one")
        return None
    return opts or RerunOptions("save", str(out / "demo.rrd"), getattr(args, "rerun_recording_id", None))


def render_timeline(records: Sequence[Mapping[str, Any]], report: Mapping[str, Any], path: Path) -> None:
    """The demo's ``pictures/timeline.png``: the one ToR plot (:func:`scmr_mesh.scenario.report.plot_tor`)."""
    from scmr_mesh.scenario.plots import plot_tor

    plot_tor(report, path, records=records)


def _frame_rgb(rec: Mapping[str, Any], images: Path | None):
    """The frame a record was about, if it can be rebuilt (synthetic) or read."""
    import cv2

    name = str(rec.get("image") or "")
    stem = name.rsplit(".", 1)[0]
    kind, _, seed = stem.rpartition("-")
    try:
        from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene

        if kind in SCENE_KINDS and seed.isdigit():
            return make_scene(kind, seed=int(seed))[0]
    except ImportError:
        pass
    if images is not None and (images / name).is_file():
        bgr = cv2.imread(str(images / name), cv2.IMREAD_COLOR)
        if bgr is not None:
            return cv2.cvtColor(cv2.resize(bgr, (300, 225), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    return None


def _pick(recs: list[Mapping[str, Any]], faults: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """Up to three records of one robot: before, during and after the first fault."""
    ok = [r for r in recs if r.get("ok")]
    if not ok:
        return []
    if not faults:
        return [ok[0], ok[len(ok) // 2], ok[-1]]
    f = faults[0]
    s, e = f["start_unix_ns"], f.get("end_unix_ns") or float("inf")
    before = [r for r in ok if r["received_unix_ns"] < s]
    during = [r for r in ok if s <= r["sent_unix_ns"] < e]
    after = [r for r in ok if r["sent_unix_ns"] >= e and r.get("tier") == "cloud"]
    return [x for x in (before[-1:] + during[:1] + after[:1])]


def render_overlays(records: Sequence[Mapping[str, Any]], report: Mapping[str, Any], out: Path, path: Path,
                    *, images: Path | None = None) -> int:
    """Tile frames blended with their received masks (green drivable, red not).

    One row per robot: the last answer before the outage, the first during it
    and the first from the cloud after it, each labelled with robot, sequence
    number, serving tier and ToR.  Returns the number of tiles drawn.
    """
    import cv2
    import numpy as np

    by_robot: dict[str, list] = {}
    for r in records:
        by_robot.setdefault(str(r.get("robot")), []).append(r)
    rows = []
    tiles = 0
    for rid in sorted(by_robot):
        recs = sorted(by_robot[rid], key=lambda r: r["sent_unix_ns"])
        row = []
        for r in _pick(recs, report.get("faults", [])):
            mask = cv2.imread(str(out / "robots" / rid / "inbox" / f"{r['seq']}.mask.png"), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                continue
            h, w = mask.shape
            colour = np.zeros((h, w, 3), np.uint8)
            colour[mask > 127] = (0, 200, 0)
            colour[mask <= 127] = (0, 0, 220)
            rgb = _frame_rgb(r, images)
            if rgb is not None and rgb.shape[:2] == (h, w):
                tile = cv2.addWeighted(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), 0.55, colour, 0.45, 0)
            else:
                tile = colour
            tile = cv2.copyMakeBorder(tile, 22, 4, 4, 4, cv2.BORDER_CONSTANT, value=(255, 255, 255))
            label = f"{rid} #{r['seq']} {r.get('tier')} {r.get('tor_ms', 0):.0f} ms"
            cv2.putText(tile, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TIER_BGR.get(r.get("tier"), (0, 0, 0)),
                        1, cv2.LINE_AA)
            row.append(tile)
            tiles += 1
        if row:
            while len(row) < 3:
                row.append(np.full_like(row[0], 255))
            rows.append(np.hstack(row))
    if rows:
        width = max(r.shape[1] for r in rows)
        rows = [cv2.copyMakeBorder(r, 0, 0, 0, width - r.shape[1], cv2.BORDER_CONSTANT, value=(255, 255, 255))
                for r in rows]
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), np.vstack(rows))
    return tiles
