"""Does `scmr ros` sending reduced frames change the masks?  (issue 26, target 5; docs/BENCHMARKS.md)

    PYTHONPATH=. python scripts/ros_reduced_mask_agreement.py [FOLDER]

For each PNG/JPEG in FOLDER (default ../shared/data/roads/images), resized to 640x480, runs the
drivable pipeline (``best``) on: the lossless raw frame (the reference), the 640x480 JPEG 90 that
`scmr robot` and `scmr ros --full-frames` send, the 320x240 JPEG 90 that `scmr ros` sends by
default (:func:`scmr_mesh.mesh.ros.reduced_for_service`), and the 640x480 JPEG 95 (how much a
small change of input moves the pipeline anyway).  Prints, per variant, the pixel agreement and
the drivable IoU of its 640x480 mask with the reference's, and the service's median time.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from scmr_mesh.imaging import encode_jpeg
from scmr_mesh.mesh.ros import mask_for, reduced_for_service
from scmr_mesh.mesh.work import process_frame


def _mask(data: bytes, encoding: str, shape=None):
    t0 = time.perf_counter()
    png = process_frame(data, encoding=encoding, shape=shape)["mask_png"]
    return mask_for(png, 480, 640) > 0, (time.perf_counter() - t0) * 1e3


def main(folder: str) -> None:
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise SystemExit(f"no PNG/JPEG files in {folder}; give a folder of road frames")
    cv2.setNumThreads(1)
    out: dict[str, list] = {"jpeg90 640x480": [], "jpeg90 320x240 (scmr ros)": [], "jpeg95 640x480": []}
    for f in files:
        rgb = cv2.resize(cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB), (640, 480), interpolation=cv2.INTER_AREA)
        ref, _ = _mask(rgb.tobytes(), "raw", (480, 640, 3))
        for name, data in zip(out, (encode_jpeg(rgb, quality=90), encode_jpeg(reduced_for_service(rgb), quality=90),
                                    encode_jpeg(rgb, quality=95))):
            m, ms = _mask(data, "jpeg")
            union = (m | ref).sum()
            out[name].append(((m == ref).mean(), (m & ref).sum() / union if union else 1.0, ms))
    print(f"{len(files)} frames from {folder}, against the lossless 640x480 frame's mask:")
    for name, rows in out.items():
        a = np.array(rows)
        print(f"  {name:26s} agreement mean {a[:, 0].mean():.4f} min {a[:, 0].min():.4f}; IoU mean {a[:, 1].mean():.4f} "
              f"median {np.median(a[:, 1]):.4f} min {a[:, 1].min():.4f}; service {np.median(a[:, 2]):.1f} ms")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).resolve().parents[2] / "shared" / "data" / "roads" / "images"))
