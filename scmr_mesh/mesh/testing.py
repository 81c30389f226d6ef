"""Testing helpers for the mesh (public: other areas' tests use them too).

:func:`stub_process` is a cheap, deterministic process function (``--process
scmr_mesh.mesh.testing:stub_process``) that needs neither numba nor the
pipeline: the mask marks as drivable every pixel of the 300x225 frame whose
grey value is at least the frame's mean.  :func:`slow_process` sleeps first
(``SCMR_STUB_DELAY_MS``, default 200) to keep requests in flight.
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
    ok, buf = cv2.imencode(".png", mask)
    return {
        "mask_png": buf.tobytes(),
        "shape": (225, 300),
        "threshold": thr,
        "timings_ms": {"stub": (time.perf_counter() - t0) * 1e3},
    }


def slow_process(image: bytes, *, encoding: str, shape, mode: str = "best") -> dict:
    """:func:`stub_process` after a sleep of ``SCMR_STUB_DELAY_MS`` ms (default 200)."""
    time.sleep(float(os.environ.get("SCMR_STUB_DELAY_MS", "200")) / 1e3)
    return stub_process(image, encoding=encoding, shape=shape, mode=mode)


def synthetic_png(seed: int = 0, *, height: int = 120, width: int = 160) -> bytes:
    """A small PNG road-like frame (grey road in the bottom centre), seeded."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    img = rng.integers(0, 80, size=(height, width, 3), dtype=np.uint8)
    img[height // 2:, width // 4: 3 * width // 4] = 150 + rng.integers(0, 20, dtype=np.uint8)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()
