"""What `best` paints green on the KITTI frames that their binary labels call not road (issue 27; docs/ACCURACY.md)

    PYTHONPATH=. python scripts/kitti_false_green.py SOURCE [ROADS]

SOURCE is a checkout of CaioChaves/Road-Detection-KITTI (the repository the shared
``kitti_semantics`` frames come from; commit 6f71e08691b9458efc3ea676dee5ef958cf5717b read
2026-11-29), ROADS the shared data folder (default $SCMR_SHARED/data/roads, else
../shared/data/roads).  Nothing is copied: the script reads the source's full Cityscapes-style
labels (``data_semantics/training/semantic/``, 1242x375, ids as in Cityscapes: 7 road,
8 sidewalk, 9 parking, 10 rail track, ...) in place, crops them as the shared frames were
cropped (rows 5-374, columns 18-1241; SOURCES.md), checks that ``id == 7`` equals the shared
binary mask pixel for pixel at 300x225, and prints per frame:

- the frame's precision under its shared label;
- the classes of its false-green pixels (the mask green, the label not road);
- the precision if a parking strip counted as ground a robot can drive.

For the one ``kitti_road`` frame (a binary label, no classes) it splits the false-green pixels
left and right of each row's labelled road centre (:func:`split_false_green`), and prints the
precision if the right-hand part counted as road.  In ``um_000000`` that part is the cycle track
right of the road: behind a row of low stone kerbs, up to the solid white line that parts it
from the footway by the wall (a cyclist rides on it); the false green of the rows without road
is the frame's bottom two rows, which the label leaves not road under the road.
"""

from __future__ import annotations

import os
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from scmr_mesh.errors import ConfigError, InputError
from scmr_mesh.imaging.codec import load_frame
from scmr_mesh.imaging.evaluate import labels_at_frame, load_manifest, score
from scmr_mesh.imaging.pipeline import segment_drivable

#: Cityscapes label ids (the source's ``semantic/`` files) named in the output.
CITYSCAPES = {0: "unlabeled", 4: "static", 5: "dynamic", 6: "ground", 7: "road", 8: "sidewalk",
              9: "parking", 10: "rail track", 11: "building", 12: "wall", 13: "fence", 17: "pole",
              19: "traffic light", 20: "traffic sign", 21: "vegetation", 22: "terrain", 23: "sky",
              24: "person", 25: "rider", 26: "car", 27: "truck", 28: "bus", 32: "motorcycle",
              33: "bicycle"}
ROAD, PARKING = 7, 9
CROP = (slice(5, None), slice(18, None))


def _kitti_semantics(item, source: Path) -> tuple[float, float, Counter]:
    name = item.image.name.removeprefix("kitti_semantics_")
    path = source / "data_semantics" / "training" / "semantic" / name
    full = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if full is None or full.ndim != 2 or full.shape[0] <= CROP[0].start or full.shape[1] <= CROP[1].start:
        raise SystemExit(f"cannot read a label image at {path}: give a checkout of CaioChaves/Road-Detection-KITTI "
                         "as SOURCE")
    road, valid, _ = labels_at_frame(item)
    sem = cv2.resize(full[CROP], (road.shape[1], road.shape[0]), interpolation=cv2.INTER_NEAREST)
    if not np.array_equal(sem == ROAD, road):
        raise SystemExit(f"{path}: its road class does not match the shared mask {item.mask.name}")
    green = segment_drivable(load_frame(item.image)).mask > 0
    classes = Counter(sem[green & ~road & valid].tolist())
    drivable = road | (sem == PARKING)
    return score(green, road, valid)["precision"], score(green, drivable, valid)["precision"], classes


def split_false_green(green: np.ndarray, road: np.ndarray,
                      valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The false-green pixels (green, valid, not road) left and right of each row's labelled road centre.

    Returns ``(left, right, off)``, bool masks that partition the false green: a row with road
    splits at the midpoint of its leftmost and rightmost road pixel (the midpoint column counts
    as right); ``off`` holds the false green of the rows without road.
    """
    false = green & ~road & valid
    right, rows = np.zeros_like(false), road.any(axis=1)
    for y in np.flatnonzero(rows):
        xs = np.flatnonzero(road[y])
        right[y, int(np.ceil((xs.min() + xs.max()) / 2)):] = True
    return false & rows[:, None] & ~right, false & right, false & ~rows[:, None]


def _kitti_road(item) -> tuple[float, float, int, int, int]:
    road, valid, _ = labels_at_frame(item)
    green = segment_drivable(load_frame(item.image)).mask > 0
    left, right, off = split_false_green(green, road, valid)
    return (score(green, road, valid)["precision"], score(green, road | right, valid)["precision"],
            int(left.sum()), int(right.sum()), int(off.sum()))


def main(source: str, roads: str) -> None:
    try:
        items = [it for it in load_manifest(roads) if it.dataset in ("kitti_semantics", "kitti_road")]
    except (InputError, ConfigError) as e:
        raise SystemExit(f"{e} (ROADS: the shared data folder, e.g. ../shared/data/roads)") from None
    if not items:
        raise SystemExit(f"no kitti frames in {roads}/manifest.json")
    labels = Path(source) / "data_semantics" / "training" / "semantic"
    if any(it.dataset == "kitti_semantics" for it in items) and not labels.is_dir():
        raise SystemExit(f"no folder {labels}: give a checkout of CaioChaves/Road-Detection-KITTI as SOURCE")
    shipped, parked, total = [], [], Counter()
    for it in items:
        if it.dataset == "kitti_road":
            p, p_right, left, right, above = _kitti_road(it)
            print(f"{it.image.name}: precision {p:.3f}; false green {left} px left of the road's centre, "
                  f"{right} right, {above} in rows without road; with the right-hand strip as road {p_right:.3f}")
            continue
        p, p_parking, classes = _kitti_semantics(it, Path(source))
        shipped.append(p)
        parked.append(p_parking)
        total.update(classes)
        top = ", ".join(f"{CITYSCAPES.get(k, k)} {v}" for k, v in classes.most_common(5))
        print(f"{it.image.name}: precision {p:.3f}, with parking drivable {p_parking:.3f}; "
              f"false green {sum(classes.values())} px: {top}")
    if shipped:
        n = sum(total.values())
        share = ", ".join(f"{CITYSCAPES.get(k, k)} {v / n:.3f}" for k, v in total.most_common(6))
        print(f"kitti_semantics: precision {np.mean(shipped):.3f}, with parking drivable {np.mean(parked):.3f}; "
              f"false green {n} px: {share}")


if __name__ == "__main__":
    args = sys.argv[1:]
    if "-h" in args or "--help" in args:
        print(__doc__)
        sys.exit(0)
    if len(args) not in (1, 2):
        sys.exit("usage: python scripts/kitti_false_green.py SOURCE [ROADS] (--help says what SOURCE is)")
    shared = Path(os.environ.get("SCMR_SHARED", Path(__file__).resolve().parents[2] / "shared"))
    main(args[0], args[1] if len(args) == 2 else str(shared / "data" / "roads"))
