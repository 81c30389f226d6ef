"""The work a service runs per request, in a pool of worker processes.

A *process function* takes the request's image fields and returns the reply's
payload fields::

    fn(image: bytes, *, encoding: str, shape: list | None, mode: str) -> dict
        {"mask_png": bytes, "shape": (225, 300), "threshold": int,
         "timings_ms": {stage: ms}}

It is named by a spec string ``"module:function"`` so worker processes can
import it (:data:`DEFAULT_PROCESS` runs the drivable-region pipeline).  If the
function has a ``warm_up`` attribute, the service calls it once before it
forks the workers, so they start warm (the pipeline's kernels, OpenCV's
codecs); a ``preload`` attribute imports what the function needs (timed as its
own start-up phase).

:class:`WorkerPool` wraps a :class:`concurrent.futures.ProcessPoolExecutor`
whose workers are forked *before* the zenoh session exists (zenoh's Rust
threads must not be forked), pre-started and warmed, and die with their parent
(``PR_SET_PDEATHSIG`` plus a watchdog thread), so a SIGKILLed service leaves no
orphans.
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Callable

from scmr_mesh import deathsig
from scmr_mesh.errors import ConfigError

log = logging.getLogger(__name__)

#: The pipeline process function.
DEFAULT_PROCESS = "scmr_mesh.mesh.work:process_frame"

_FN: Callable[..., dict] | None = None
#: In a worker: the pool's shared count of frames its workers have finished (see WorkerPool.outstanding)
_DONE = None


def resolve(spec: str) -> Callable[..., dict]:
    """Import ``"module:function"`` and return the function.

    Raises
    ------
    ConfigError
        When the spec is malformed or does not name a callable.
    """
    mod, sep, name = str(spec).partition(":")
    if not sep or not mod or not name:
        raise ConfigError(f"process function must be 'module:function', got {spec!r}")
    try:
        fn = getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"cannot load process function {spec!r}: {exc}") from None
    if not callable(fn):
        raise ConfigError(f"{spec!r} is not callable")
    return fn


def preload(fn: Callable[..., Any]) -> None:
    """Call ``fn.preload()`` (import what it needs) when the process function has one."""
    p = getattr(fn, "preload", None)
    if callable(p):
        p()


def warm(fn: Callable[..., Any]) -> None:
    """Call ``fn.warm_up()`` when the process function has one."""
    w = getattr(fn, "warm_up", None)
    if callable(w):
        w()


def process_frame(image: bytes, *, encoding: str, shape: list | None, mode: str = "best") -> dict:
    """Run the drivable-region pipeline on one encoded frame.

    Parameters
    ----------
    image : bytes
        PNG/JPEG bytes, or raw RGB rows when ``encoding == "raw"``.
    encoding : {"png", "jpeg", "raw"}
    shape : list of int or None
        ``[H, W, 3]`` for raw frames.
    mode : {"best", "thesis"}

    Returns
    -------
    dict
        ``mask_png`` (PNG of the (225, 300) uint8 0/255 mask), ``shape``,
        ``threshold``, ``timings_ms`` (per stage, plus ``decode`` and ``encode``), and
        ``confidence`` and ``abstained`` (``best``'s calibrated abstention; None in ``thesis``).
    """
    from scmr_mesh.imaging import decode_frame, encode_mask_png, segment_drivable
    from scmr_mesh.imaging.codec import MAX_PNG_FRAME_PIXELS

    t0 = time.perf_counter()
    rgb = decode_frame(image, shape=tuple(shape[:2]) if encoding == "raw" and shape else None,
                       max_png_pixels=MAX_PNG_FRAME_PIXELS)
    t1 = time.perf_counter()
    res = segment_drivable(rgb, mode=mode)
    t2 = time.perf_counter()
    png = encode_mask_png(res.mask)
    t3 = time.perf_counter()
    timings = {str(k): float(v) for k, v in dict(getattr(res, "timings_ms", {}) or {}).items()}
    timings["decode"] = (t1 - t0) * 1e3
    timings["encode"] = (t3 - t2) * 1e3
    timings.setdefault("pipeline", (t2 - t1) * 1e3)
    return {
        "mask_png": png,
        "shape": tuple(res.mask.shape[:2]),
        "threshold": int(res.threshold),
        "timings_ms": timings,
        "confidence": getattr(res, "confidence", None),
        "abstained": getattr(res, "abstained", None),
    }


def _load_pipeline() -> None:
    import scmr_mesh.imaging.codec  # noqa: F401  numpy, OpenCV
    import scmr_mesh.imaging.pipeline  # noqa: F401


def warm_png() -> bytes:
    """A 160x120 road-like PNG made without numpy.random (7 ms less to import), for warm-ups."""
    import cv2
    import numpy as np

    h, w = 120, 160
    img = ((np.arange(h * w * 3, dtype=np.uint32) * 2654435761) >> 26).astype(np.uint8).reshape(h, w, 3)
    img[h // 2:, w // 4: 3 * w // 4] = 150 + img[h // 2:, w // 4: 3 * w // 4] % 20
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


def _warm_pipeline() -> None:
    # every step of a request: PNG decode, the kernels (AOT module loaded, or
    # numba compiled / loaded from its cache), PNG encode.  With the AOT kernels
    # the thesis mode's first frame costs ~1.6 ms more, not worth 7 ms of every
    # start; the numba JIT would compile its kernels then, so warm it too.
    from scmr_mesh.imaging import _aot

    png = warm_png()
    process_frame(png, encoding="png", shape=None, mode="best")
    if not _aot.status().startswith("aot"):
        process_frame(png, encoding="png", shape=None, mode="thesis")


process_frame.preload = _load_pipeline  # type: ignore[attr-defined]
process_frame.warm_up = _warm_pipeline  # type: ignore[attr-defined]


# ------------------------------------------------------------------- workers
def _die_with_parent(parent_pid: int) -> None:
    deathsig.set_in_this_process(signal.SIGKILL)   # Linux: SIGKILL this worker when its parent thread dies

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(0)
            time.sleep(0.25)

    threading.Thread(target=watch, name="scmr-parent-watch", daemon=True).start()


def _init_worker(spec: str, parent_pid: int, warmed: bool = False, done=None) -> None:
    global _FN, _DONE
    _DONE = done
    # the parent owns shutdown: a SIGTERM/Ctrl-C sent to the whole process group
    # must not kill a worker in the middle of a frame the service is draining;
    # workers still die with the parent (PR_SET_PDEATHSIG) and on pool shutdown
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    _FN = resolve(spec)
    if not warmed:  # forked from the warmed service: nothing left to warm
        warm(_FN)


class Expired(Exception):
    """The robot's deadline passed before a worker got to the request."""


def _run(image: bytes, encoding: str, shape, mode: str, expires_mono: float | None = None) -> dict:
    assert _FN is not None
    try:
        if expires_mono is not None and time.monotonic() > expires_mono:
            # the robot has given up and re-sent elsewhere: skip the work (CLOCK_MONOTONIC
            # is system-wide, so the service's arrival-based expiry is valid here)
            raise Expired(f"deadline passed {1e3 * (time.monotonic() - expires_mono):.0f} ms before a worker was free")
        t0 = time.perf_counter()
        out = _FN(image, encoding=encoding, shape=shape, mode=mode)
        out["worker_ms"] = (time.perf_counter() - t0) * 1e3
        return out
    finally:  # this worker is free now, before its result reaches the service (see WorkerPool.outstanding)
        if _DONE is not None:
            with _DONE.get_lock():
                _DONE.value += 1


def _ping() -> int:
    return os.getpid()


def _kernel_status(process: str) -> str:
    """Which pipeline kernels this process loaded (AOT or numba JIT), for the start-up log."""
    if process != DEFAULT_PROCESS:
        return "n/a"
    import sys

    aot = sys.modules.get("scmr_mesh.imaging._aot")
    return aot.status() if aot is not None else "unknown"


class WorkerPool:
    """A pool of warmed worker processes running one process function.

    Parameters
    ----------
    workers : int
        Number of worker processes (>= 1).
    process : str
        ``"module:function"`` spec of the process function.

    Notes
    -----
    Create it before opening any zenoh session: the workers are forked and
    started in the constructor, and :meth:`start` waits until each has warmed
    up.
    """

    def __init__(self, workers: int, *, process: str = DEFAULT_PROCESS, clock=None) -> None:
        import multiprocessing as mp

        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        # fail early, in the parent, with a clear message; warming here first
        # means the forked workers inherit the loaded kernels and warmed caches
        fn = resolve(process)
        preload(fn)
        if clock is not None:
            clock.mark("pipeline imports")
        warm(fn)
        if clock is not None:
            clock.mark("kernels + warm-up run", kernels=_kernel_status(process))
        self._clock = clock
        self.workers = int(workers)
        self.process = process
        self.restarts = 0
        self._respawn_lock = threading.Lock()
        self._count_lock = threading.Lock()
        self._submitted = 0
        self._done = mp.get_context("fork").Value("q", 0)
        self._executor = ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=mp.get_context("fork"),
            initializer=_init_worker,
            initargs=(process, os.getpid(), True, self._done),
        )

    def start(self, *, timeout: float = 300.0) -> list[int]:
        """Start and warm every worker; return their pids.

        Raises
        ------
        MeshError
            When a worker fails to start or warm up.
        """
        from scmr_mesh.errors import MeshError

        try:
            futs = [self._executor.submit(_ping) for _ in range(self.workers)]
            for f in futs:
                f.result(timeout=timeout)
        except Exception as exc:
            raise MeshError(f"worker pool failed to start ({type(exc).__name__}: {exc})") from None
        return self.pids()

    def pids(self) -> list[int]:
        """The worker processes' pids."""
        procs = getattr(self._executor, "_processes", None) or {}
        return sorted(procs)

    def submit(self, image: bytes, *, encoding: str, shape, mode: str, expires_mono: float | None = None) -> Future:
        """Queue one frame; the future yields the process function's dict.

        ``expires_mono`` (``time.monotonic()`` seconds): a worker that reaches the
        frame later raises :class:`Expired` instead of running the pipeline.

        A pool whose worker died (killed, out of memory, a crash in native code on a
        hostile image) is broken for good in :mod:`concurrent.futures`: the request in
        flight fails, and the next submit replaces the pool so the service keeps serving.
        """
        from concurrent.futures.process import BrokenProcessPool

        try:
            return self._submit_counted(image, encoding, shape, mode, expires_mono)
        except BrokenProcessPool:
            self._respawn()
            return self._submit_counted(image, encoding, shape, mode, expires_mono)

    def _submit_counted(self, image, encoding, shape, mode, expires_mono) -> Future:
        # the pool and its count change together (see _respawn): a frame is counted for the pool
        # it went to, never for a pool that replaced it meanwhile
        with self._count_lock:
            fut = self._executor.submit(_run, image, encoding, shape, mode, expires_mono)
            self._submitted += 1
            return fut

    def outstanding(self) -> int:
        """Frames submitted that no worker has finished yet (waiting or being worked on).

        Counted from the workers' side (a shared counter each worker bumps as it
        finishes a frame), so a frame whose result is still on its way back to
        the service (the result pipe, the pool's collecting thread, the
        interpreter lock of a busy service) no longer counts: its worker is free.
        The service's own in-flight count includes those, and on a loaded host
        it priced work that was already done (issue 23 item 2).
        """
        with self._count_lock:
            submitted = self._submitted
        return max(0, submitted - int(self._done.value))

    def _respawn(self) -> None:
        """Replace a broken pool.  New workers are *spawned* (not forked): zenoh's
        threads exist by now and must not be forked."""
        import multiprocessing as mp

        with self._respawn_lock:
            old = self._executor
            if not getattr(old, "_broken", False):  # another thread already replaced it
                return
            self.restarts += 1
            log.error("a worker process died; starting a new pool of %d (restart %d)", self.workers, self.restarts)
            # the old pool's frames fail: count afresh (the service's in-flight count still bounds admission)
            done = mp.get_context("spawn").Value("q", 0)
            with self._count_lock:  # the new pool and its count together (see _submit_counted)
                self._submitted, self._done = 0, done
                self._executor = ProcessPoolExecutor(
                    max_workers=self.workers,
                    mp_context=mp.get_context("spawn"),
                    initializer=_init_worker,
                    initargs=(self.process, os.getpid(), False, done),
                )
            try:
                old.shutdown(wait=False, cancel_futures=True)
            except Exception as exc:  # pragma: no cover
                log.debug("broken pool shutdown: %s", exc)

    def shutdown(self) -> None:
        """Stop the workers (pending work is cancelled)."""
        try:
            self._executor.shutdown(wait=True, cancel_futures=True)
        except Exception as exc:  # pragma: no cover
            log.warning("worker pool shutdown: %s", exc)
