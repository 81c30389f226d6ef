"""``scmr bench pipeline``: per-stage timing of :func:`segment_drivable`.

Runs in one process pinned to one core (``os.sched_setaffinity``) with numba
and OpenCV limited to one thread, after JIT warm-up.  ``total`` is the time
from a 300x225 RGB array to the mask; ``decode`` (PNG bytes to RGB) and
``resize`` (source size to 300x225) are measured separately.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


def _pin_one_core() -> int | None:
    try:
        cpus = sorted(os.sched_getaffinity(0))
        core = cpus[-1]
        os.sched_setaffinity(0, {core})
        return core
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return None


def _frames(images: Path | None, limit: int = 64) -> list[tuple[str, bytes]]:
    """Encoded frames to cycle through: real images from a folder, else synthetic scenes."""
    from scmr_mesh.errors import InputError
    from scmr_mesh.imaging.codec import encode_png

    if images is not None:
        if not Path(images).is_dir():
            raise InputError(f"--images must be a folder of PNG/JPEG files, got {images}")
        files = sorted(
            p for p in Path(images).rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg") and p.is_file()
        )
        # a manifest folder: use the photos, not the label masks
        if (Path(images) / "images").is_dir():
            files = [p for p in files if "images" in p.parts]
        if not files:
            raise InputError(f"no PNG/JPEG files in {images}")
        return [(p.name, p.read_bytes()) for p in files[:limit]]
    from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene

    out = []
    for seed in range(4):
        for kind in SCENE_KINDS:
            rgb, _ = make_scene(kind, seed=seed, width=640, height=480)
            out.append((f"{kind}:{seed}", encode_png(rgb)))
    return out


def bench_pipeline(
    *,
    frames: int = 200,
    images: Path | None = None,
    mode: str = "best",
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Time the pipeline stages over ``frames`` frames.

    Returns
    -------
    dict
        ``{"frames", "mode", "core", "sources", "median_ms": {stage: ms, ...,
        "total": ms}, "p99_ms": {...}}``; stages include ``decode`` and
        ``resize``, which are not part of ``total``.  ``cpu_total_median_ms`` is
    the thread CPU time of the same calls (robust to a busy machine) and
    ``load_average`` the 1/5/15-minute load when the run ended.
    """
    import cv2
    import numba

    from scmr_mesh.errors import InputError
    from scmr_mesh.imaging.codec import decode_image, resize_frame
    from scmr_mesh.imaging.pipeline import segment_drivable, warm_up

    if frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    core = _pin_one_core()
    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    sources = _frames(images)
    decoded = [decode_image(data) for _, data in sources]
    ready = [resize_frame(rgb) for rgb in decoded]
    warm_up()
    for f in ready[: min(len(ready), 5)]:
        segment_drivable(f, mode=mode)

    samples: dict[str, list[float]] = {"decode": [], "resize": []}
    cpu: list[float] = []
    # decode and resize are timed in their own pass, so decoding a large file
    # does not flush the caches just before each timed pipeline run
    for i in range(frames):
        j = i % len(sources)
        t0 = time.perf_counter()
        rgb = decode_image(sources[j][1])
        t1 = time.perf_counter()
        resize_frame(rgb)
        t2 = time.perf_counter()
        samples["decode"].append((t1 - t0) * 1000)
        samples["resize"].append((t2 - t1) * 1000)
        if progress and (i % 20 == 0 or i == frames - 1):
            progress(i + 1, 2 * frames)
    for i in range(frames):
        j = i % len(sources)
        c0 = time.thread_time()
        res = segment_drivable(ready[j], mode=mode)
        cpu.append((time.thread_time() - c0) * 1000)
        for k, v in res.timings_ms.items():
            if k != "resize":
                samples.setdefault(k, []).append(v)
        if progress and (i % 20 == 0 or i == frames - 1):
            progress(frames + i + 1, 2 * frames)
    median = {k: round(float(np.median(v)), 4) for k, v in samples.items()}
    p99 = {k: round(float(np.percentile(v, 99)), 4) for k, v in samples.items()}
    h, w = decoded[0].shape[:2]
    return {
        "frames": frames,
        "mode": mode,
        "core": core,
        "sources": {"n": len(sources), "from": str(images) if images else "synthetic 640x480 PNG", "first_size": [w, h]},
        "median_ms": median,
        "p99_ms": p99,
        # CPU time of the whole segment_drivable call (this thread only): much less
        # sensitive than wall time to other processes competing for the core
        "cpu_total_median_ms": round(float(np.median(cpu)), 4),
        "cpu_total_p99_ms": round(float(np.percentile(cpu, 99)), 4),
        "load_average": _loadavg(),
    }


def _loadavg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return None


# ------------------------------------------------------------------ CLI
def cmd_bench_pipeline(args: argparse.Namespace) -> int:
    from scmr_mesh.imaging.commands import _write_json

    tty = sys.stderr.isatty()

    def progress(i: int, n: int) -> None:
        if tty:
            print(f"\rtimed {i}/{n} runs (decode pass, then pipeline pass)", end="" if i < n else "\n",
                  file=sys.stderr, flush=True)
        elif i == n or i % max(1, n // 5) == 0:  # a few whole lines in logs and CI
            print(f"timed {i}/{n} runs (decode pass, then pipeline pass)", file=sys.stderr)

    print("warming up (numba JIT / cache) ...", file=sys.stderr)
    result = bench_pipeline(frames=args.frames, images=args.images, mode=args.mode, progress=progress)
    med, p99 = result["median_ms"], result["p99_ms"]
    print(f"{'stage':10s} {'median ms':>10s} {'p99 ms':>10s}")
    for k in med:
        print(f"{k:10s} {med[k]:10.3f} {p99[k]:10.3f}")
    print(f"{'total CPU':10s} {result['cpu_total_median_ms']:10.3f} {result['cpu_total_p99_ms']:10.3f}")
    if result.get("load_average"):
        print(f"load average during the run: {result['load_average']} (wall-clock figures include waiting for the core)")
    if args.json:
        _write_json(args.json, result)
    return 0
