"""Testing helpers for the mesh (public: other areas' tests use them too).

:func:`stub_process` is a cheap, deterministic process function (``--process
scmr_mesh.mesh.testing:stub_process``) that needs neither numba nor the
pipeline: the mask marks as drivable every pixel of the 300x225 frame whose
grey value is at least the frame's mean.  :func:`slow_process` sleeps first
(``SCMR_STUB_DELAY_MS``, default 200) to keep requests in flight.
:func:`fixed_process` only sleeps (``SCMR_STUB_DELAY_MS``, default 100) and
replies a constant mask: a fixed service time with no CPU work.
"""

from __future__ import annotations

import os
import time


def stub_process(image: bytes, *, encoding: str, shape, mode: str = "best") -> dict:
    """Threshold the frame at its mean grey (see module docstring)."""
    import cv2
    import numpy as np

    t0 = time.perf_counter()
    if encoding == "raw":
        h, w = int(shape[0]), int(shape[1])
        if len(image) != h * w * 3:
            from scmr_mesh.errors import ImageDecodeError

            raise ImageDecodeError(f"raw frame of shape {list(shape)} needs {h * w * 3} bytes, got {len(image)}")
        rgb = np.frombuffer(image, dtype=np.uint8).reshape(h, w, 3)
    else:
        arr = cv2.imdecode(np.frombuffer(image, dtype=np.uint8), cv2.IMREAD_COLOR)
        if arr is None:
            from scmr_mesh.errors import ImageDecodeError

            raise ImageDecodeError(f"cannot decode {len(image)} bytes as {encoding}")
        rgb = arr[:, :, ::-1]
    small = cv2.resize(np.ascontiguousarray(rgb), (300, 225), interpolation=cv2.INTER_AREA)
    grey = small.mean(axis=2)
    thr = int(grey.mean())
    mask = np.where(grey >= thr, 255, 0).astype(np.uint8)
    from scmr_mesh.imaging.codec import encode_mask_png

    return {
        "mask_png": encode_mask_png(mask),  # as the pipeline's masks (work.py)
        "shape": (225, 300),
        "threshold": thr,
        "timings_ms": {"stub": (time.perf_counter() - t0) * 1e3},
    }


def _warm_stub() -> None:
    stub_process(synthetic_png(0), encoding="png", shape=None)


stub_process.warm_up = _warm_stub  # type: ignore[attr-defined]


def slow_process(image: bytes, *, encoding: str, shape, mode: str = "best") -> dict:
    """:func:`stub_process` after a sleep of ``SCMR_STUB_DELAY_MS`` ms (default 200).

    With ``SCMR_STUB_MARK_DIR`` set, first writes an empty file
    ``<dir>/<time_ns>.start`` so a test can wait until a frame is being worked on.
    """
    mark_dir = os.environ.get("SCMR_STUB_MARK_DIR")
    if mark_dir:
        open(os.path.join(mark_dir, f"{time.time_ns()}.start"), "wb").close()
    time.sleep(float(os.environ.get("SCMR_STUB_DELAY_MS", "200")) / 1e3)
    return stub_process(image, encoding=encoding, shape=shape, mode=mode)


slow_process.warm_up = _warm_stub  # type: ignore[attr-defined]


_FIXED_MASK: bytes | None = None


def _fixed_mask() -> bytes:
    global _FIXED_MASK
    if _FIXED_MASK is None:
        import numpy as np

        mask = np.zeros((225, 300), np.uint8)
        mask[112:, 75:225] = 255  # the bottom centre is road
        from scmr_mesh.imaging.codec import encode_mask_png

        _FIXED_MASK = encode_mask_png(mask)
    return _FIXED_MASK


def fixed_process(image: bytes, *, encoding: str, shape, mode: str = "best") -> dict:
    """A fixed service time and no CPU work: sleep ``SCMR_STUB_DELAY_MS`` ms (default 100), reply a constant mask.

    What ``scmr bench scale`` runs on the cloud nodes, so that the capacity
    measured is the cloud tier's (workers x nodes / service time), not the
    host's two cores.  The frame is not decoded.
    """
    delay_ms = float(os.environ.get("SCMR_STUB_DELAY_MS", "100"))
    time.sleep(delay_ms / 1e3)
    return {"mask_png": _fixed_mask(), "shape": (225, 300), "threshold": 128, "timings_ms": {"fixed": delay_ms}}


fixed_process.warm_up = _fixed_mask  # type: ignore[attr-defined]


def synthetic_png(seed: int = 0, *, height: int = 120, width: int = 160) -> bytes:
    """A small PNG road-like frame (grey road in the bottom centre), seeded."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    img = rng.integers(0, 80, size=(height, width, 3), dtype=np.uint8)
    img[height // 2:, width // 4: 3 * width // 4] = 150 + rng.integers(0, 20, dtype=np.uint8)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


# ------------------------------------------------------------ processes
STUB = "scmr_mesh.mesh.testing:stub_process"
SLOW = "scmr_mesh.mesh.testing:slow_process"
FIXED = "scmr_mesh.mesh.testing:fixed_process"


def spawn_peer(args: list[str], *, log_path, env: dict | None = None, prefix: list[str] = ()):
    """Start ``python -m scmr_mesh ARGS`` in its own process group, logging to ``log_path``.

    ``prefix`` is prepended to the command (e.g. ``["ip", "netns", "exec", NS]``).

    Returns the :class:`subprocess.Popen`; stop it with :func:`stop_peer`.
    """
    import subprocess
    import sys

    full_env = dict(os.environ)
    full_env.pop("RUST_LOG", None)
    full_env.update(env or {})
    log = open(log_path, "ab")
    try:
        return subprocess.Popen([*prefix, sys.executable, "-m", "scmr_mesh", *args], stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=full_env, start_new_session=True)
    finally:
        log.close()


def stop_peer(proc, *, sig: int | None = None, timeout: float = 10.0) -> int | None:
    """Signal a peer's process group (SIGTERM by default), wait, SIGKILL if needed; return its status."""
    import signal
    import subprocess

    sig = signal.SIGTERM if sig is None else sig
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        try:  # a peer that will not stop: its threads' stacks into its log, then SIGKILL
            os.kill(proc.pid, signal.SIGUSR1)
            time.sleep(0.5)
        except ProcessLookupError:
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        return proc.wait(timeout=5)
    finally:
        try:  # leftovers of the group (workers) when only the leader died
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def wait_for(predicate, *, timeout: float = 60.0, interval: float = 0.05, what: str = "condition") -> None:
    """Poll ``predicate()`` until true; raise TimeoutError naming ``what``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


def read_records(path) -> list[dict]:
    """The records of a robot's ``records.jsonl`` (complete lines only)."""
    import json
    from pathlib import Path

    p = Path(path)
    if not p.exists():
        return []
    out = []
    for line in p.read_text().splitlines():
        if line.strip():
            try:
                out.append(json.loads(line))
            except ValueError:
                break
    return out
