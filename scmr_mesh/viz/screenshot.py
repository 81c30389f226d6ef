"""Screenshots of recordings; and: record a small fleet run from real road images and screenshot it headless.

:func:`screenshot` renders any ``.rrd`` headless (``scmr view --screenshot``).
:func:`main` is a check-by-looking tool for the rerun viewer, not part of the
test suite.  It logs N robots through the same code path the fleet uses (a
:class:`scmr_mesh.viz.FleetViz` sink in --save mode, one :class:`RobotViz`
per robot connected with the child arguments), with drivability maps from
``scmr_mesh.imaging.pipeline.segment_drivable`` on the images in
``--data`` (read in place), a cloud outage in the middle (tier drops from
cloud to leader), then renders the recording in rerun's headless viewer.

    .venv/bin/python -m scmr_mesh.viz.screenshot --data ../shared/data/roads \
        --rrd /tmp/viz-shot.rrd --png docs/img/viewer.png

Needs ``apt-get install -y mesa-vulkan-drivers`` for the headless viewer.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from scmr_mesh.errors import InputError
from scmr_mesh.ports import free_port
from scmr_mesh.viz.common import ViewerError
from scmr_mesh.viz.rerun_cli import check_rrd, rerun_env, rerun_executable


def _use_rerun_env_here() -> None:
    """Point this process's XDG dirs at :func:`state_dir` (for viewers rerun spawns itself)."""
    env = rerun_env()
    os.environ["XDG_CONFIG_HOME"] = env["XDG_CONFIG_HOME"]
    os.environ["XDG_DATA_HOME"] = env["XDG_DATA_HOME"]


def screenshot(
    path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    settle: float = 6.0,
    max_size: int | None = None,
    port: int | None = None,
) -> Path:
    """Render a ``.rrd`` in rerun's headless native viewer and save a PNG.

    Needs a Vulkan driver (Debian: ``apt-get install -y mesa-vulkan-drivers``,
    the lavapipe software renderer); without one the viewer panics with
    "Failed to get render context".  Meant for the CLI (``scmr view
    --screenshot``): it points this process's XDG dirs at :func:`state_dir`.

    Parameters
    ----------
    path : path-like
        The recording.
    out : path-like
        PNG to write.
    settle : float
        Seconds to wait after opening (chunks load lazily).
    max_size : int, optional
        Longest side of the PNG in pixels (default: the viewer's 1920x1080).
    port : int, optional
        Port of the headless viewer (default: a free one).

    Returns
    -------
    Path
        ``out``.
    """
    rrd = check_rrd(path)
    out = Path(out)
    if not out.parent.exists():
        raise InputError(f"--screenshot {out}: folder {out.parent} does not exist")
    _use_rerun_env_here()
    from rerun.experimental import ViewerClient

    port = port or free_port()
    try:
        client = ViewerClient.spawn(
            headless=True, port=port, executable_path=rerun_executable(), hide_welcome_screen=True
        )
    except Exception as exc:  # the bindings raise plain exceptions
        raise ViewerError(
            f"the headless rerun viewer did not start ({exc}); it needs a Vulkan driver: "
            "apt-get install -y mesa-vulkan-drivers"
        ) from exc
    try:
        client.open(str(rrd.resolve()))
        time.sleep(settle)
        png = client.take_screenshot(max_size=max_size)
    except Exception as exc:
        raise ViewerError(
            f"the headless rerun viewer could not render {rrd} ({type(exc).__name__}: {exc}); "
            "a Vulkan driver is needed: apt-get install -y mesa-vulkan-drivers"
        ) from exc
    finally:
        for closer in ("quit", "close"):
            try:
                getattr(client, closer)()
            except Exception:  # already gone
                pass
        pid = getattr(client, "_pid", None)
        if pid:
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    out.write_bytes(png)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="the roads folder (with manifest.json)")
    ap.add_argument("--rrd", default="/tmp/viz-shot.rrd")
    ap.add_argument("--png", default="docs/img/viewer.png")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--settle", type=float, default=8.0)
    args = ap.parse_args(argv)

    from scmr_mesh import viz
    from scmr_mesh.imaging.codec import load_image
    from scmr_mesh.imaging.pipeline import segment_drivable

    data = Path(args.data)
    manifest = json.loads((data / "manifest.json").read_text())
    images = sorted((data / "images").glob("*.png"))[: args.robots]
    robots = [f"r{i}" for i in range(len(images))]
    frames = {}
    for r, path in zip(robots, images):
        rgb = load_image(path)
        res = segment_drivable(rgb, stages=True)
        frames[r] = (rgb, res.mask, res.stages["srm"])
        print(f"{r}: {path.name} drivable {np.mean(res.mask > 0):.0%}", file=sys.stderr)
    del manifest

    fv = viz.FleetViz(viz.RerunOptions("save", args.rrd), robots=robots)
    rid = fv.recording_id
    rvs = {r: viz.RobotViz(viz.RerunOptions("connect", fv.url, rid), r) for r in robots}
    t0 = time.time_ns()
    step = 200_000_000  # 0.2 s per request
    fv.log_alive("cloud", "cloud0", True, t_unix_ns=t0)
    fv.log_alive("leader", "leader0", True, t_unix_ns=t0)
    outage = (args.frames // 3, 2 * args.frames // 3)
    fv.log_fault({"kind": "crash", "target": "cloud0", "tier": "cloud",
                  "start_unix_ns": t0 + outage[0] * step, "end_unix_ns": t0 + outage[1] * step})
    fv.log_alive("cloud", "cloud0", False, t_unix_ns=t0 + outage[0] * step + 2_000_000)
    fv.log_alive("cloud", "cloud0", True, t_unix_ns=t0 + outage[1] * step + 250_000_000)
    rng = np.random.default_rng(5)
    for i in range(args.frames):
        tier = "leader" if outage[0] <= i < outage[1] else "cloud"
        for k, r in enumerate(robots):
            rgb, mask, srm = frames[r]
            tor = float(rng.normal(40 if tier == "cloud" else 70, 5))
            rec = {"robot": r, "seq": i, "ok": True, "tier": tier, "served_by": f"{tier}0",
                   "sent_unix_ns": t0 + i * step, "received_unix_ns": t0 + i * step + int(tor * 1e6),
                   "tor_ms": tor, "energy_j": 1.0 + 0.1 * k, "battery": 1.0 - 0.01 * i}
            rvs[r].observe(rec, rgb, mask, srm=srm)
            fv.log_record(rec)
    for rv in rvs.values():
        rv.close()
    path = fv.close()
    print(f"saved {path}", file=sys.stderr)
    t = time.perf_counter()
    viz.screenshot(path, args.png, settle=args.settle)
    print(f"wrote {args.png} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
