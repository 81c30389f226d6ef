"""The pipeline's faster ways to the same bytes: each checked against the computation it replaced.

Issue 27's time target (``scmr bench pipeline --reference``): ``best``'s working-frame resize,
its seed selection, its gradient, the cell's Otsu counts and the mask's threshold were each
replaced by a faster computation of the same values.  These tests hold each to the old one on
random inputs (Hypothesis) and on edge cases.  That the masks, thresholds, confidences and
reasons of the 60 road frames and the synthetic scenes stayed the same to the byte was checked
when the change was made, by hashing them under the old and the new code (docs/BENCHMARKS.md,
"`best` in 0.8 ms less"); no test here pins those bytes (a pinned hash would break on any
honest change of the road model).
"""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.imaging import _aot, steps
from scmr_mesh.imaging.codec import area_resize
from scmr_mesh.imaging.road_model import WORK_SHAPE, _seeds_grounded, grey_gradient, seed_regions
from scmr_mesh.imaging.steps import bottom_centre, roi


# ----------------------------------------------------------------- area resize, 2:1 across
@settings(max_examples=120, deadline=None)
@given(h=st.integers(2, 120), half_w=st.integers(1, 90), fy=st.floats(0.34, 0.99),
       seed=st.integers(0, 2**32 - 1), flat=st.booleans())
def test_an_exact_half_across_with_a_fractional_down_gives_opencv_s_bytes(h, half_w, fy, seed, flat):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, 2 * half_w, 3), dtype=np.uint8)
    if flat:  # sums landing on .5 exactly, where a different rounding would show
        rgb[: h // 2] = rng.integers(0, 256, 3, dtype=np.uint8)
    height = max(1, min(h, round(h * fy)))
    out = area_resize(rgb, half_w, height)
    np.testing.assert_array_equal(out, cv2.resize(rgb, (half_w, height), interpolation=cv2.INTER_AREA))


def test_a_read_only_frame_is_copied_for_the_kernel_s_one_signature(monkeypatch):
    seen = []
    real = _aot.kernel("area_half_kernel")
    monkeypatch.setattr(_aot, "area_half_kernel", lambda *a: seen.append(a[0].flags.writeable) or real(*a),
                        raising=False)
    rgb = np.random.default_rng(6).integers(0, 256, (225, 300, 3), dtype=np.uint8)
    rgb.setflags(write=False)
    wh, ww = WORK_SHAPE
    out = area_resize(rgb, ww, wh)
    assert seen == [True]  # a read-only array would make numba compile a second version
    np.testing.assert_array_equal(out, cv2.resize(rgb, (ww, wh), interpolation=cv2.INTER_AREA))


def test_best_s_working_frame_takes_the_one_pass_kernel(monkeypatch):
    calls = []
    real = _aot.kernel("area_half_kernel")
    monkeypatch.setattr(_aot, "area_half_kernel", lambda *a: calls.append(a[0].shape) or real(*a), raising=False)
    rgb = np.random.default_rng(5).integers(0, 256, (225, 300, 3), dtype=np.uint8)
    wh, ww = WORK_SHAPE
    out = area_resize(rgb[:, ::-1], ww, wh)  # a strided view is copied first
    assert calls == [(225, 900)]
    np.testing.assert_array_equal(out, cv2.resize(np.ascontiguousarray(rgb[:, ::-1]), (ww, wh),
                                                  interpolation=cv2.INTER_AREA))


# ----------------------------------------------------------------- seeds
def _seeds_reference(labels, n_regions, share, lateral):
    """seed_regions and _grounded as they were written before (issue 27, commit 1dc046a)."""
    cell = bottom_centre(roi(labels))
    counts = np.bincount(cell.ravel(), minlength=n_regions)
    low = np.bincount(cell[cell.shape[0] // 2:].ravel(), minlength=n_regions)
    grounded = bool(np.any((counts >= share * cell.size) & (low > 0)))
    seeds = np.flatnonzero((counts >= share * cell.size) & (low > 0))
    if seeds.size == 0:
        seeds = np.flatnonzero(low > 0)
    if lateral > 0 and seeds.size > 1:
        h, w = labels.shape
        top = h - cell.shape[0]
        lo, hi = lateral * (w - 1), (1 - lateral) * (w - 1)
        main = seeds[np.argmax(counts[seeds])]
        keep = []
        for s in seeds.tolist():
            if s != main:
                cols = np.count_nonzero(labels == s, axis=0)
                centre = float(cols @ np.arange(w)) / max(int(cols.sum()), 1)
                if not lo <= centre <= hi and (labels[:top] == s).any():
                    continue
            keep.append(s)
        seeds = np.array(keep, dtype=seeds.dtype)
    return seeds, grounded


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), block=st.integers(1, 40), n=st.integers(1, 12),
       share=st.sampled_from([0.02, 0.1, 0.3]), lateral=st.sampled_from([0.0, 0.1, 0.25, 0.45]))
def test_seeds_and_ground_contact_are_the_ones_the_per_seed_loop_found(seed, block, n, share, lateral):
    rng = np.random.default_rng(seed)
    h, w = 112, 150
    # blocky labels (regions of many shapes, some beside the cell, some running up the frame)
    coarse = rng.integers(0, n, (-(-h // block), -(-w // block)))
    labels = np.repeat(np.repeat(coarse, block, 0), block, 1)[:h, :w].astype(np.int32)
    if rng.random() < 0.5:  # a tall stripe beside the cell, as a verge is
        x0 = int(rng.integers(0, w - 5))
        labels[int(rng.integers(0, h)):, x0:x0 + 5] = n
    k = int(labels.max()) + 1
    got, grounded = _seeds_grounded(labels, k, share, lateral)
    want, want_grounded = _seeds_reference(labels, k, share, lateral)
    assert got.tolist() == want.tolist() and grounded == want_grounded
    assert seed_regions(labels, k, share, lateral).tolist() == want.tolist()


# ----------------------------------------------------------------- gradient
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), h=st.integers(1, 60), w=st.integers(1, 60), flat=st.booleans())
def test_the_grey_gradient_is_the_correctly_rounded_magnitude_of_float_sobels(seed, h, w, flat):
    rng = np.random.default_rng(seed)
    grey = rng.integers(0, 256, (h, w), dtype=np.uint8)
    if flat:
        grey[:, : w // 2] = 255
    f = grey.astype(np.float32)
    gx, gy = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
    want = np.sqrt(gx.astype(np.float64) ** 2 + gy.astype(np.float64) ** 2).astype(np.float32)
    got = grey_gradient(grey)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)
    # and the same whatever the input's place in memory (cv2.magnitude's result was not)
    buf = np.empty(grey.size + 64, np.uint8)
    for off in (1, 3, 8, 17):
        moved = buf[off:off + grey.size].reshape(grey.shape)
        moved[:] = grey
        np.testing.assert_array_equal(grey_gradient(moved), want)


# ----------------------------------------------------------------- Otsu over few bins
@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 80), top=st.sampled_from([1, 3, 50, 5000, 10**6]),
       ties=st.booleans())
def test_the_python_loop_over_few_bins_picks_numpy_s_threshold(seed, k, top, ties):
    rng = np.random.default_rng(seed)
    h = np.zeros(256, np.int64)
    bins = rng.choice(256, k, replace=False)
    h[bins] = 7 if ties else rng.integers(1, top + 1, k)
    loop = steps._OTSU_LOOP_BINS
    got = steps.otsu_of_counts(h)
    steps._OTSU_LOOP_BINS = 0  # the numpy scan (not a fixture: Hypothesis runs many examples per call)
    try:
        want = steps.otsu_of_counts(h)
    finally:
        steps._OTSU_LOOP_BINS = loop
    assert got == want


def test_huge_counts_do_not_wrap_whatever_the_number_of_bins():
    # before: the numpy scan's int64 products wrapped above a total of about 2e8 (3e9 / 1e9 / 3e9
    # gave 10, not 100); scaling every count by one factor leaves Otsu's threshold where it was
    small = np.zeros(256, np.int64)
    small[[10, 100, 200]] = [3, 1, 3]
    assert steps.otsu_of_counts(small) == steps.otsu_of_counts(small * 10**9) == 100
    rng = np.random.default_rng(11)
    for k in (3, 40, 100, 256):  # below and above the loop's bin limit
        h = np.zeros(256, np.int64)
        h[rng.choice(256, k, replace=False)] = rng.integers(1, 1000, k)
        assert steps.otsu_of_counts(h * 10**9) == steps.otsu_of_counts(h), k


def test_the_mask_threshold_is_np_where_s_on_every_byte():
    up = np.arange(256, dtype=np.uint8).reshape(16, 16)
    np.testing.assert_array_equal(cv2.threshold(up, 127, 255, cv2.THRESH_BINARY)[1],
                                  np.where(up >= 128, 255, 0).astype(np.uint8))
