"""The cut of the candidate's rough surfaces (``RoadParams.rough``, :func:`cut_rough`) and its blur guard.

Analytic scenes on the 300x225 frame: cobbles beside smooth asphalt are cut, bright paint on the
asphalt is not rough (and is, with the paint clip off: the clip is what keeps it), one texture
everywhere is nothing, rough ground in the robot's path stays, bands across the road take nothing
beyond them; a road blurred in part is no rough surface (each half of the blur guard alone keeps
it, and without the guard it is cut); the kernels against numpy; and the shared road frames,
where the cut lifts KITTI's cobbled pavement and costs no frame, also with part of each frame
blurred; and the strong blur over the bottom centre the guard misses, why the cut is off by
default.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.errors import InputError
from scmr_mesh.imaging._srm_kernels import rough_rows_kernel, row_medians_kernel
from scmr_mesh.imaging.codec import FRAME_SHAPE, area_resize, load_frame
from scmr_mesh.imaging.evaluate import labels_at_frame, load_manifest, score
from scmr_mesh.imaging.pipeline import DEFAULT_PARAMS, best_mask_from, segment_drivable, working_frame
from scmr_mesh.imaging.road_model import WORK_SHAPE, RoadParams, blur_spread, cut_rough, rough_surface, sharpness_maps
from scmr_mesh.imaging import road_model

#: the cut on (it is off by default: test_a_strong_blur_over_the_bottom_centre_fools_the_guard...) and off
ROUGH = dataclasses.replace(DEFAULT_PARAMS, rough=1.75)
OFF = dataclasses.replace(DEFAULT_PARAMS, rough=0.0)
FH, FW = FRAME_SHAPE
H, W = WORK_SHAPE
FY, FX = np.mgrid[0:FH, 0:FW]


def _cobbles(seed: int = 1) -> np.ndarray:
    """Stones of 4x4 frame pixels, each its own grey in 70..140, with 1 px dark joints."""
    rng = np.random.default_rng(seed)
    stones = rng.integers(70, 141, (FH // 4 + 1, FW // 4 + 1))
    img = stones[FY // 4, FX // 4].astype(float)
    img[(FY % 4 == 0) | (FX % 4 == 0)] = 45
    return img


def _frame(cobbles: np.ndarray | None = None, paint: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """Smooth grey asphalt (100, noise 1.5), cobbles where ``cobbles`` (bool, frame), white paint where ``paint``."""
    grey = np.full((FH, FW), 100.0) + np.random.default_rng(seed).normal(0, 1.5, (FH, FW))
    if cobbles is not None:
        grey[cobbles] = _cobbles()[cobbles]
    if paint is not None:
        grey[paint] = 235
    g = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    return np.dstack([g, g, g])


def _candidate() -> np.ndarray:
    c = np.zeros((H, W), np.uint8)
    c[H // 3:] = 1
    return c


def _small(frame: np.ndarray) -> np.ndarray:
    return area_resize(frame, W, H)


#: the pavement: the frame's right quarter
PAVEMENT = FX >= 3 * FW // 4


def test_cobbles_beside_smooth_asphalt_are_rough_and_cut():
    frame = _frame(cobbles=PAVEMENT)
    small, cand = _small(frame), _candidate()
    rough = rough_surface(cand, small, frame, 1.75)
    pav = np.zeros((H, W), bool)
    pav[:, 3 * W // 4 + 3:] = True          # away from the seam the 5x5 box straddles
    judged = cand > 0
    assert rough[pav & judged].mean() > 0.9
    assert not rough[:, : 3 * W // 4 - 3].any()   # no asphalt
    out = cut_rough(cand, small, frame, 1.75)
    assert out is not cand and not (out[pav] > 0).any()
    assert (out[:, : 3 * W // 4 - 3] == cand[:, : 3 * W // 4 - 3]).all()


def _no_blur_guard(monkeypatch) -> None:
    """The blur guard off: no frame is uneven enough, no surface sharp enough, to be spared."""
    monkeypatch.setattr(road_model, "ROUGH_BLUR_SPREAD", float("inf"))
    monkeypatch.setattr(road_model, "ROUGH_SHARPER", float("inf"))


def test_paint_on_asphalt_is_not_rough_because_of_the_clip(monkeypatch):
    """Lane lines and a hatched box junction: bright, thin and many edges.  The clip at the row's
    median + ROUGH_PAINT flattens them; with the clip off (255) and the blur guard off (the paint's
    edges are sharper than the asphalt's grain, and the guard would spare them too) the same frame
    has rough surfaces: the clip, not luck, keeps the paint."""
    lines = (np.abs(FX - FW // 2) <= 1) | (np.abs(FX - FW // 4) <= 1) | (np.abs(FX - 3 * FW // 4) <= 1)
    hatch = (FY > FH // 2) & (((FX + FY) % 12) < 2) & (FX > FW // 3) & (FX < 2 * FW // 3)
    frame = _frame(paint=lines | hatch)
    small, cand = _small(frame), _candidate()
    assert not rough_surface(cand, small, frame, 1.75).any()
    assert cut_rough(cand, small, frame, 1.75) is cand
    monkeypatch.setattr(road_model, "ROUGH_PAINT", 255)
    _no_blur_guard(monkeypatch)
    assert rough_surface(cand, small, frame, 1.75).any()


def test_one_texture_everywhere_is_not_rough():
    """Rough is relative to the candidate's median in the row: a cobbled street is its own road."""
    frame = _frame(cobbles=np.ones((FH, FW), bool))
    small, cand = _small(frame), _candidate()
    assert not rough_surface(cand, small, frame, 1.75).any()


def test_rough_ground_in_the_robots_path_stays(monkeypatch):
    """What reaches into the robot's path (the centre columns) is ground it drives on.  A cobbled lane
    under the robot, straight up the frame, is kept by the path rule alone (off, it is rough).  A
    gravel strip under the robot converging ahead, and a band of cobbles across the road at an angle
    (a hostile review's scenes: with a guard on the bottom-centre cell instead, both were cut, and
    everything beyond the band with it) are kept; with the three rules off (path, beside, beyond)
    both are rough.  The same strip beside the path, with no road beyond it, is cut."""
    cand = _candidate()
    lane = (FX >= FW // 4) & (FX < 3 * FW // 4 - 30)
    frame = _frame(cobbles=lane)
    assert not rough_surface(cand, _small(frame), frame, 1.75).any()
    t = np.clip((FY - 75) / (FH - 1 - 75), 0, 1)
    strip = (FX >= np.rint(148 - 23 * t)) & (FX < np.rint(152 + 23 * t)) & (FY >= 75)
    a = 175 - 60 * FX / (FW - 1)
    band = (FY >= a) & (FY < a + 24)
    for where in (strip, band):
        frame = _frame(cobbles=where)
        assert not rough_surface(cand, _small(frame), frame, 1.75).any()
        assert cut_rough(cand, _small(frame), frame, 1.75) is cand
    beside = (FX >= 240) & (FX < 280) & (FY >= 75)
    frame = _frame(cobbles=beside)
    assert rough_surface(cand, _small(frame), frame, 1.75)[60:, 122:138].all()
    monkeypatch.setattr(road_model, "ROUGH_PATH", -1)   # ww // 2 + 1 : ww // 2: no column
    frame = _frame(cobbles=lane)
    assert rough_surface(cand, _small(frame), frame, 1.75).any()
    monkeypatch.setattr(road_model, "ROUGH_BESIDE", H)
    monkeypatch.setattr(road_model, "ROUGH_BEYOND", float("inf"))
    for where in (strip, band):
        frame = _frame(cobbles=where)
        assert rough_surface(cand, _small(frame), frame, 1.75).any()


def _band_scene(seed: int, y0: int, slope: int, thick: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth asphalt to a horizon at row 85 and a band of 2 px gravel across it at an angle."""
    r = np.random.default_rng(seed)
    img = np.empty((FH, FW, 3))
    img[:85] = (150, 180, 225)
    img[85:] = 100 + r.normal(0, 2, (FH - 85, FW, 1))
    grain = np.kron(r.normal(0, 35, (FH // 2 + 1, FW // 2)), np.ones((2, 2)))[:FH, :FW]
    band = (FY >= y0 + slope * (FX - FW // 2) / (FW // 2)) & (FY < y0 + thick + slope * (FX - FW // 2) / (FW // 2))
    band &= FY > 85
    img[band] = 100 + grain[band][:, None]
    truth = np.zeros((FH, FW), np.uint8)
    truth[85:] = 255
    return np.clip(img, 0, 255).astype(np.uint8), truth


#: bands across the road that the path rule alone let the cut take, with the road beyond them
BANDS = [(1, 150, -60, 32), (0, 150, -60, 24), (0, 210, -30, 24), (1, 170, 30, 24), (0, 210, 30, 24),
         (1, 190, -30, 24)]


@pytest.mark.parametrize("seed,y0,slope,thick", BANDS)
def test_a_band_across_the_road_takes_nothing_beyond_it(monkeypatch, seed, y0, slope, thick):
    """A band of gravel across the road, seen at an angle, lies beside the path in part: cutting that
    part took the road beyond it (the column fill stops at the cut; IoU -0.29 to -0.37 with the path
    rule alone).  A surface that does not reach the bottom ROUGH_BESIDE rows lies ahead, and one
    with more than ROUGH_BEYOND x its area of road beyond it is a band: neither is cut.  Off, the
    loss comes back (the test of the test)."""
    img, truth = _band_scene(seed, y0, slope, thick)
    base = score(segment_drivable(img, params=OFF).mask, truth)["iou"]
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] >= base - 0.02
    monkeypatch.setattr(road_model, "ROUGH_BESIDE", H)
    monkeypatch.setattr(road_model, "ROUGH_BEYOND", float("inf"))
    _no_blur_guard(monkeypatch)   # the band's 2 px grain is coarser than the asphalt's: it spares it too
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] < base - 0.2


#: bands that the road-beyond rule alone let the cut take: they lie ahead, not beside the robot
BANDS_AHEAD = [(1, 150, -30, 24), (1, 160, 60, 32), (0, 120, 30, 32)]


@pytest.mark.parametrize("seed,y0,slope,thick", BANDS_AHEAD)
def test_a_band_ahead_is_not_beside_the_robot(monkeypatch, seed, y0, slope, thick):
    """Bands whose rough part beside the path has little road beyond it in its columns, but which
    do not reach the frame's bottom rows: the ROUGH_BESIDE rule keeps them (off, they lose 0.13-0.24
    of IoU with the road-beyond rule alone, 2026-11-29)."""
    img, truth = _band_scene(seed, y0, slope, thick)
    base = score(segment_drivable(img, params=OFF).mask, truth)["iou"]
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] >= base - 0.02
    monkeypatch.setattr(road_model, "ROUGH_BESIDE", H)
    _no_blur_guard(monkeypatch)
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] < base - 0.1


def test_a_frame_of_another_size_is_refused():
    """The texture is read at the 300x225 frame's pixel pitch: another size would misplace it."""
    frame = np.zeros((240, 320, 3), np.uint8)
    with pytest.raises(ValueError, match="300x225"):
        rough_surface(_candidate(), _small(_frame()), frame, 1.75)


def test_what_the_cut_detaches_goes_and_what_was_apart_stays():
    """The candidate: the robot's road, a neck of cobbles on the left joining a smooth patch beyond
    it, and a smooth piece apart from everything.  The neck is cut; the patch it joined goes with
    it; the piece that was apart before stays (as in the boundary cut)."""
    cand = np.zeros((H, W), np.uint8)
    cand[60:, 50:100] = 1                 # the robot's road (covers the bottom-centre cell)
    cand[70:, 20:50] = 1                  # the neck, cobbled, beside the robot down to the bottom
    cand[70:, 0:20] = 1                   # the patch beyond it
    cand[40:50, 120:140] = 1              # a piece apart
    cob = np.zeros((FH, FW), bool)
    cob[140:, 40:100] = True              # the neck in frame pixels
    frame = _frame(cobbles=cob)
    out = cut_rough(cand, _small(frame), frame, 1.75)
    assert (out[60:, 55:100] == 1).all()
    assert not out[75:, 25:45].any()
    assert not out[70:, 0:20].any()
    assert (out[40:50, 120:140] == 1).all()


def test_off_empty_and_degenerate_inputs():
    frame = _frame(cobbles=PAVEMENT)
    small, cand = _small(frame), _candidate()
    assert cut_rough(cand, small, frame, 0.0) is cand
    empty = np.zeros((H, W), np.uint8)
    assert cut_rough(empty, small, frame, 1.75) is empty
    few = np.zeros((H, W), np.uint8)
    few[100:, 70:79] = 1                 # 9 pixels a row: no row is judged
    assert not rough_surface(few, small, frame, 1.75).any()
    for value in (0, 255):
        flat = np.full((FH, FW, 3), value, np.uint8)
        assert cut_rough(cand, _small(flat), flat, 1.75) is cand


@pytest.mark.parametrize("bad", [1.0, 0.5, -1.0, float("inf"), float("nan")])
def test_rough_must_be_off_or_above_one(bad):
    with pytest.raises(InputError, match="rough must be 0"):
        RoadParams(rough=bad).check()
    RoadParams(rough=0.0).check()


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 12), st.integers(1, 40), st.integers(0, 2**32 - 1), st.integers(0, 20))
def test_row_medians_kernel_is_numpys_median(rows, cols, seed, min_count):
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 256, (rows, cols), dtype=np.uint8)
    mask = (rng.random((rows, cols)) < rng.random()).astype(np.uint8)
    got = row_medians_kernel(values, mask, min_count)
    for y in range(rows):
        sel = values[y][mask[y] > 0]
        if sel.size < max(min_count, 1):
            assert np.isnan(got[y])
        else:
            assert got[y] == np.float32(np.median(sel))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1.25, 1.75, 3.0]))
def test_rough_rows_kernel_is_its_numpy_reading(seed, ratio):
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 60, (20, 30), dtype=np.uint8)
    mask = (rng.random((20, 30)) < 0.6).astype(np.uint8)
    out, count = rough_rows_kernel(texture, mask, ratio, 10)
    want = np.zeros_like(out)
    for y in range(20):
        sel = texture[y][mask[y] > 0]
        if sel.size >= 10:
            want[y] = (mask[y] > 0) & (texture[y] > ratio * max(float(np.median(sel)), 1.0))
    assert (out == want).all() and count == int(want.sum())


def test_the_working_frame_path_gives_segment_drivables_mask(roads_dir):
    """best_mask_from(working_frame(...)) carries the 300x225 frame the cut reads: the same mask."""
    item = next(it for it in load_manifest(roads_dir) if it.image.name == "kitti_semantics_000004_10.png")
    rgb = load_frame(item.image)
    assert (best_mask_from(working_frame(rgb, ROUGH), ROUGH)[0] == segment_drivable(rgb, params=ROUGH).mask).all()


def test_on_the_shared_frames_the_cut_lifts_kittis_cobbles_and_costs_no_frame(roads_dir):
    """KITTI semantics 000004: the cobbled pavement on the right joined the road by colour (precision
    0.619 without the cut, 0.773 with it, 2026-11-29).  Over the 60 frames no mask loses more than
    0.01 of IoU and at least four gain 0.015 (KITTI road, ORFD 2, KITTI semantics 2 and 4)."""
    gains, losses = [], []
    for item in load_manifest(roads_dir):
        rgb = load_frame(item.image)
        road, valid, _ = labels_at_frame(item)
        with_cut = score(segment_drivable(rgb, params=ROUGH).mask, road, valid)
        without = score(segment_drivable(rgb, params=OFF).mask, road, valid)
        d = with_cut["iou"] - without["iou"]
        (gains if d >= 0.015 else losses if d < -0.01 else []).append(item.image.name)
        if item.image.name == "kitti_semantics_000004_10.png":
            assert without["precision"] < 0.65 and with_cut["precision"] > 0.75
    assert not losses, losses
    assert len(gains) >= 4, gains


def _blur_part(img: np.ndarray, part: np.ndarray, sigma: float) -> np.ndarray:
    """``img`` (300x225, changed in place and returned) blurred at ``sigma`` where ``part`` (bool)."""
    blurred = cv2.GaussianBlur(img, (0, 0), sigma)
    img[part] = blurred[part]
    return img


def _blurred_road(where: str, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A straight smooth road (grey 100, grain 3) to a horizon at row 85, part of it blurred."""
    rng = np.random.default_rng(0)
    img = np.empty((FH, FW, 3))
    img[:85] = (150, 180, 225)
    img[85:] = 100 + rng.normal(0, 3, (FH - 85, FW, 1))
    img = np.clip(img, 0, 255).astype(np.uint8)
    part = {"left": FX < 3 * FW // 5, "right": FX >= 2 * FW // 5,
            "drop": np.hypot(FX - 140, FY - 160) < 95}[where]
    img = _blur_part(img, part, sigma)
    truth = np.zeros((FH, FW), np.uint8)
    truth[85:] = 255
    return img, truth


@pytest.mark.parametrize("where", ["left", "right", "drop"])
@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_partial_blur_is_no_rough_surface(monkeypatch, where, sigma):
    """A blur over most of a row (a water drop, mud, motion blur on part of the lens) lowers the row's
    median texture, and the sharp road beside it reads as rough: without the blur guard a straight
    road with its left 60 % blurred loses a third of its IoU under the cut (a second hostile review,
    2026-11-29; on the shared frames blurred so, mean IoU 0.783 -> 0.634).  Each half of the guard
    alone keeps the road here: the frame's uneven sharpness (ROUGH_BLUR_SPREAD) and the surface
    sharper than the road beside it (ROUGH_SHARPER); with both off the loss comes back."""
    img, truth = _blurred_road(where, sigma)
    sharper = road_model.ROUGH_SHARPER
    base = score(segment_drivable(img, params=OFF).mask, truth)["iou"]
    assert base > 0.95
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] >= base - 0.01
    monkeypatch.setattr(road_model, "ROUGH_SHARPER", float("inf"))
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] >= base - 0.01
    monkeypatch.setattr(road_model, "ROUGH_SHARPER", sharper)
    monkeypatch.setattr(road_model, "ROUGH_BLUR_SPREAD", float("inf"))
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] >= base - 0.01
    monkeypatch.setattr(road_model, "ROUGH_SHARPER", float("inf"))
    assert score(segment_drivable(img, params=ROUGH).mask, truth)["iou"] < base - 0.1


def test_blur_spread_is_low_in_one_focus_and_high_with_part_blurred():
    """The frame's sharpness spread: one texture in one focus measures near 1, the same frame with
    its left 60 % blurred (sigma 1.2) above ROUGH_BLUR_SPREAD; scaling the contrast changes nothing
    (|Laplacian| and |gradient| scale alike); a frame with too few blocks of edges is not judged."""
    grain = np.clip(100 + np.random.default_rng(0).normal(0, 3, (FH, FW, 1)), 0, 255).astype(np.uint8)
    cob = _frame(cobbles=np.ones((FH, FW), bool))
    for frame in (np.repeat(grain, 3, axis=2), cob):
        lap, grad = sharpness_maps(frame)
        assert blur_spread(lap, grad) < 1.3
        assert blur_spread(3 * lap, 3 * grad) == pytest.approx(blur_spread(lap, grad))
    part = cv2.GaussianBlur(cob, (0, 0), 1.2)
    cob[:, : 3 * FW // 5] = part[:, : 3 * FW // 5]
    assert blur_spread(*sharpness_maps(cob)) > 1.5 * road_model.ROUGH_BLUR_SPREAD   # 3.1
    flat = np.full((FH, FW, 3), 120, np.uint8)
    flat[:40, :100] = _frame(cobbles=np.ones((FH, FW), bool))[:40, :100]   # 2 edged blocks
    assert blur_spread(*sharpness_maps(flat)) == 1.0


def _left_blurred(rgb: np.ndarray) -> np.ndarray:
    """``rgb`` at 300x225 with its left 60 % blurred at sigma 1.2 (the second review's transform)."""
    return _blur_part(area_resize(rgb, FW, FH), FX < 3 * FW // 5, 1.2)


def test_on_the_shared_frames_blurred_in_part_the_guard_keeps_the_road(monkeypatch, roads_dir):
    """The second review's transform on every shared frame: its left 60 % blurred (sigma 1.2, at
    300x225).  With the guard the cut costs no frame more than 0.02 of IoU and the mean nothing
    (measured: 0.7830 off and on); with the guard off the mean falls by more than 0.1 (0.783 ->
    0.634, the reason the cut was off by default until the guard)."""
    items = load_manifest(roads_dir)
    base, on = [], []
    frames = []
    for item in items:
        road, valid, _ = labels_at_frame(item)
        rgb = _left_blurred(load_frame(item.image))
        frames.append((rgb, road, valid))
        base.append(score(segment_drivable(rgb, params=OFF).mask, road, valid)["iou"])
        on.append(score(segment_drivable(rgb, params=ROUGH).mask, road, valid)["iou"])
    base, on = np.array(base), np.array(on)
    assert (on >= base - 0.02).all(), [items[i].image.name for i in np.flatnonzero(on < base - 0.02)]
    assert on.mean() >= base.mean() - 0.002
    _no_blur_guard(monkeypatch)
    unguarded = np.array([score(segment_drivable(rgb, params=ROUGH).mask, road, valid)["iou"]
                          for rgb, road, valid in frames])
    assert unguarded.mean() < base.mean() - 0.1


def _bottom_drop(rgb: np.ndarray, sigma: float) -> np.ndarray:
    """A drop of radius 70 px over the bottom centre of the 300x225 frame, blurred at ``sigma``."""
    return _blur_part(area_resize(rgb, FW, FH), np.hypot(FX - 150, FY - 225) < 70, sigma)


def test_a_strong_blur_over_the_bottom_centre_fools_the_guard_so_the_cut_is_off_by_default(roads_dir):
    """The third review (2026-11-29): a drop of mud or water over the bottom centre of the lens,
    blurred strongly (sigma 3), makes the road on both sides of it rough, and the guard sees
    neither half: the blurred blocks fall under the gradient floor (ROUGH_BLUR_EDGES), so the
    frame's spread stays low, and the surface is no sharper than the rest of its rows, where the
    lane lines are sharp.  CamVid Seq05VD f00690 loses 0.34 of IoU (0.898 -> 0.555); over the 60
    shared frames 0.808 -> 0.754, 21 frames losing more than 0.02.  No labelled frame has a drop,
    so the cross-validation cannot see it: the cut is off by default and out of the grid.  When a
    guard makes this pass, the default can be chosen again."""
    item = next(it for it in load_manifest(roads_dir) if it.image.name == "camvid_Seq05VD_f00690.png")
    road, valid, _ = labels_at_frame(item)
    rgb = _bottom_drop(load_frame(item.image), 3.0)
    assert DEFAULT_PARAMS.rough == 0
    base = score(segment_drivable(rgb).mask, road, valid)["iou"]
    assert base > 0.85
    assert score(segment_drivable(rgb, params=ROUGH).mask, road, valid)["iou"] < base - 0.2


def test_blur_spread_never_divides_by_zero():
    """Blocks with a gradient and no curvature (a ramp of one grey level a row) gave NaN (all such
    blocks) or inf with a warning (a third review); now 1.0 for ramps only (evenly unsharp) and
    inf for a ramp beside sharp blocks (as uneven as can be: nothing is cut)."""
    ramp = np.dstack([FY.astype(np.uint8)] * 3)
    with np.errstate(all="raise"):
        assert blur_spread(*sharpness_maps(ramp)) == 1.0
        half = ramp.copy()
        half[:, FW // 2:] = np.random.default_rng(0).integers(0, 255, (FH, FW - FW // 2, 3))
        assert blur_spread(*sharpness_maps(half)) == float("inf")
