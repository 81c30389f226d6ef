"""scripts/kitti_false_green.py: the KITTI frames' false green named by class (docs/ACCURACY.md).

The source's Cityscapes-style labels are not in ../shared, so these tests build stand-ins in a
temporary folder from the shared binary masks (read in place; nothing is written into the repo).
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from scmr_mesh.imaging.evaluate import load_manifest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "kitti_false_green.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=REPO,
                          timeout=300, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})


def _script():
    spec = importlib.util.spec_from_file_location("kitti_false_green", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _items(roads_dir: Path, dataset: str):
    items = [it for it in load_manifest(roads_dir) if it.dataset == dataset]
    assert items, f"no {dataset} frames in the shared manifest"
    return items


def _source(tmp_path: Path, item, other: int) -> Path:
    """A stand-in source checkout: the shared mask's road as class 7, every other pixel ``other``."""
    mask = cv2.imread(str(item.mask), cv2.IMREAD_GRAYSCALE)
    full = np.full((mask.shape[0] + 5, mask.shape[1] + 18), other, np.uint8)
    full[5:, 18:][mask == 255] = 7
    folder = tmp_path / "data_semantics" / "training" / "semantic"
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / item.image.name.removeprefix("kitti_semantics_")), full)
    return tmp_path


def test_parking_everywhere_off_the_road_makes_every_green_pixel_drivable(roads_dir, tmp_path):
    mod = _script()
    item = _items(roads_dir, "kitti_semantics")[-1]
    p, p_parking, classes = mod._kitti_semantics(item, _source(tmp_path, item, mod.PARKING))
    assert p < 1.0 and p_parking == 1.0
    assert set(classes) == {mod.PARKING}


def test_sidewalk_everywhere_off_the_road_changes_nothing(roads_dir, tmp_path):
    mod = _script()
    item = _items(roads_dir, "kitti_semantics")[-1]
    p, p_parking, classes = mod._kitti_semantics(item, _source(tmp_path, item, 8))
    assert p_parking == p < 1.0
    assert set(classes) == {8}


def test_a_label_that_is_not_the_shared_mask_is_refused(roads_dir, tmp_path):
    mod = _script()
    item = _items(roads_dir, "kitti_semantics")[-1]
    src = _source(tmp_path, item, mod.PARKING)
    path = src / "data_semantics" / "training" / "semantic" / item.image.name.removeprefix("kitti_semantics_")
    full = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    full[-60:, :] = 7   # more road than the shared mask has
    cv2.imwrite(str(path), full)
    with pytest.raises(SystemExit, match="does not match the shared mask"):
        mod._kitti_semantics(item, src)


def test_kitti_road_false_green_splits_into_left_right_and_above_without_loss(roads_dir):
    mod = _script()
    from scmr_mesh.imaging.codec import load_frame
    from scmr_mesh.imaging.evaluate import labels_at_frame, score
    from scmr_mesh.imaging.pipeline import segment_drivable

    item = _items(roads_dir, "kitti_road")[0]
    p, p_right, left, right, above = mod._kitti_road(item)
    road, valid, _ = labels_at_frame(item)
    green = segment_drivable(load_frame(item.image)).mask > 0
    assert left + right + above == int((green & ~road & valid).sum())
    assert p == score(green, road, valid)["precision"]
    assert p <= p_right <= 1.0 and (right == 0) == (p_right == p)


def test_the_split_is_by_each_rows_road_centre():
    mod = _script()
    road = np.zeros((4, 20), bool)
    road[0, 4:8] = True      # centre 5.5: columns 6.. are right
    road[1, 10:19] = True    # centre 14: columns 14.. are right
    road[1, [12, 16]] = False  # holes in the label: 12 left of the centre, 16 right
    road[2, 3] = True        # one pixel: it is the centre, so right
    green = np.ones_like(road)
    green[1, 0] = False
    valid = np.ones_like(road)
    valid[0, 19] = False
    left, right, off = mod.split_false_green(green, road, valid)
    assert not (left & right).any() and not ((left | right) & off).any()
    assert np.array_equal(left | right | off, green & ~road & valid)
    assert np.array_equal(np.flatnonzero(left[0]), [0, 1, 2, 3])
    assert np.array_equal(np.flatnonzero(right[0]), list(range(8, 19)))
    assert np.array_equal(np.flatnonzero(left[1]), [*range(1, 10), 12])
    assert np.array_equal(np.flatnonzero(right[1]), [16, 19])
    assert np.array_equal(np.flatnonzero(left[2]), [0, 1, 2]) and right[2, 4:].all()
    assert off[3].all() and not off[:3].any()


def test_a_missing_source_is_one_line_naming_the_path(roads_dir, tmp_path):
    out = _run(str(tmp_path / "nowhere"), str(roads_dir))
    assert out.returncode == 1
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0] and "CaioChaves/Road-Detection-KITTI" in err[0], out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize("args", [("--help",), ("src", "-h"), ("src", "roads", "--help")])
def test_help_explains_and_exits(args):
    out = _run(*args)
    assert out.returncode == 0 and "SOURCE" in out.stdout and "parking" in out.stdout


@pytest.mark.parametrize("roads", ["missing", "empty", "bad_json"])
def test_a_bad_roads_folder_is_one_line(tmp_path, roads):
    folder = tmp_path / roads
    if roads != "missing":
        folder.mkdir()
    if roads == "bad_json":
        (folder / "manifest.json").write_text("{not json")
    out = _run(str(tmp_path), str(folder))
    err = out.stderr.strip().splitlines()
    assert out.returncode == 1 and len(err) == 1 and "ROADS" in err[0] and "Traceback" not in out.stderr


def test_no_arguments_is_a_usage_line(roads_dir):
    out = _run()
    assert out.returncode == 1 and out.stderr.startswith("usage:") and len(out.stderr.splitlines()) == 1
