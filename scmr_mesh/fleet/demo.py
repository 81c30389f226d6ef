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

__all__ = ["register", "render_overlays", "render_timeline"]

#: BGR colours of the serving tiers in the pictures.
TIER_BGR = {"cloud": (200, 120, 20), "leader": (0, 140, 255), "peer": (60, 170, 60), "local": (170, 40, 170),
            None: (0, 0, 230)}


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
    report = run_with_output(config, quiet=args.quiet)
    records = _load_records(out)
    pics = out / "pictures"
    pics.mkdir(exist_ok=True)
    render_timeline(records, report, pics / "timeline.png")
    render_overlays(records, report, out, pics / "overlays.png")
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


def _load_records(out: Path) -> list[dict]:
    import json

    recs = []
    for f in sorted((out / "robots").glob("*/records.jsonl")):
        for ln in f.read_text().splitlines():
            try:
                recs.append(json.loads(ln))
            except json.JSONDecodeError:
                continue
    return recs


def render_timeline(records: Sequence[Mapping[str, Any]], report: Mapping[str, Any], path: Path,
                    *, width: int = 1000, height: int = 420) -> None:
    """Draw every request's ToR against its sending time, coloured by serving tier.

    Parameters
    ----------
    records : sequence of record dicts
    report : report dict (for ``started_unix_ns`` and ``faults``)
    path : Path
        PNG written here, ``(height, width, 3) uint8``.
    """
    import cv2
    import numpy as np

    from scmr_mesh.qos import metrics

    img = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 60, 20, 40, 50
    t_ref = report.get("started_unix_ns") or (min(r["sent_unix_ns"] for r in records) if records else 0)
    xs = [(r["sent_unix_ns"] - t_ref) / 1e9 for r in records]
    t_min = min([0.0, *xs])
    t_max = max([float(report.get("duration_s", 1.0)), *xs]) or 1.0
    tors = metrics.tor_values_ms(records)
    y_max = max(20.0, metrics.percentile(tors, 99) * 1.3) if tors else 100.0

    def X(t: float) -> int:
        return int(left + (t - t_min) / (t_max - t_min) * (width - left - right))

    def Y(ms: float) -> int:
        return int(height - bottom - min(ms, y_max) / y_max * (height - top - bottom))

    moves = {c["from"]: c["to"] for c in (report.get("leadership") or {}).get("changes", []) if c.get("from")}
    for f in report.get("faults", []):
        a = (f["start_unix_ns"] - t_ref) / 1e9
        if f.get("tier") == "leader":  # the lead passes on: a marker, not a lost tier
            cv2.line(img, (X(a), top), (X(a), height - bottom), TIER_BGR["leader"], 1)
            label = f"leader {f['target']} killed" + (f" -> {moves[f['target']]} leads" if f["target"] in moves else "")
            cv2.putText(img, label, (X(a) + 4, top + 30), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 90, 160), 1,
                        cv2.LINE_AA)
            continue
        b = ((f["end_unix_ns"] - t_ref) / 1e9) if f.get("end_unix_ns") else t_max
        cv2.rectangle(img, (X(a), top), (X(b), height - bottom), (225, 225, 225), -1)
        cv2.putText(img, f"{f['target']} down", (X(a) + 4, top + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (90, 90, 90), 1, cv2.LINE_AA)
    cv2.line(img, (left, height - bottom), (width - right, height - bottom), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, height - bottom), (0, 0, 0), 1)
    for i in range(5):
        ms = y_max * i / 4
        cv2.putText(img, f"{ms:.0f}", (5, Y(ms) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    step = max(1, int(round((t_max - t_min) / 10)))
    t = int(np.ceil(t_min))
    while t <= t_max:
        cv2.putText(img, f"{t}", (X(t) - 5, height - bottom + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0),
                    1, cv2.LINE_AA)
        t += step
    cv2.putText(img, "time since the fleet was ready (s)", (width // 2 - 120, height - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "ToR (ms)", (5, top - 22), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for r, x in zip(records, xs):
        tier = r.get("tier") if r.get("ok") else None
        colour = TIER_BGR.get(tier, (0, 0, 0))
        if tier is None:
            p = (X(x), top + 4)
            cv2.drawMarker(img, p, colour, cv2.MARKER_TILTED_CROSS, 8, 2)
            continue
        tor = r.get("tor_ms") or 0.0
        cv2.circle(img, (X(x), Y(tor)), 3, colour, -1, cv2.LINE_AA)
    lx = left + 10
    for name in ("cloud", "leader", "peer", "local", None):
        label = name or "failed"
        cv2.circle(img, (lx, top - 8), 5, TIER_BGR[name], -1)
        cv2.putText(img, label, (lx + 10, top - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        lx += 90
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


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
