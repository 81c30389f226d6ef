"""``cell_otsu``: the bottom-centre cell's channel, histogram and Otsu threshold from region counts.

Cross-checked against the thesis's own steps on the cell's pixels (:func:`dominant_channel`,
:func:`histogram`, :func:`otsu_threshold` of ``palette[labels]`` over the cell), which the
pipeline ran before: on random label maps and palettes (ties between channels included), and
on the SRM results of the road frames.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.imaging.codec import decode_frame
from scmr_mesh.imaging.pipeline import _cell_index, cell_otsu, working_frame
from scmr_mesh.imaging.road_model import WORK_SHAPE
from scmr_mesh.imaging.steps import dominant_channel, histogram, otsu_of_counts, otsu_threshold


def _from_pixels(labels, palette):
    window = palette[labels[_cell_index()]]
    channel = dominant_channel(window)
    hist = histogram(np.ascontiguousarray(window[:, :, channel]))
    return channel, hist, otsu_threshold(hist)


def _same(labels, palette):
    channel, hist, threshold = cell_otsu(labels, palette)
    want = _from_pixels(labels, palette)
    assert (channel, threshold) == (want[0], want[2])
    assert hist.dtype == np.int64
    np.testing.assert_array_equal(hist, want[1])


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), regions=st.integers(1, 400), levels=st.sampled_from([2, 3, 256]),
       blocky=st.booleans())
def test_the_counts_give_the_pixels_figures_on_random_label_maps(seed, regions, levels, blocky):
    rng = np.random.default_rng(seed)
    if blocky:  # SRM-like: a few large regions, many regions with no pixel in the cell at all
        coarse = rng.integers(0, regions, (7, 10), dtype=np.int32)
        labels = np.ascontiguousarray(np.kron(coarse, np.ones((16, 15), np.int32))[: WORK_SHAPE[0], : WORK_SHAPE[1]])
    else:
        labels = rng.integers(0, regions, WORK_SHAPE, dtype=np.int32)
    # few levels: channel sums tie often (ties go to the first channel) and histograms have 1-3 bins
    palette = (rng.integers(0, levels, (regions, 3)) * (255 // max(1, levels - 1))).astype(np.uint8)
    _same(labels, palette)


def test_one_region_and_a_uniform_cell():
    labels = np.zeros(WORK_SHAPE, np.int32)
    palette = np.array([[40, 40, 40]], np.uint8)
    assert cell_otsu(labels, palette)[::2] == (0, 40)  # one occupied bin: that value, as otsu_threshold says
    _same(labels, palette)


def test_the_road_frames_srm_results(roads_dir):
    items = json.loads((roads_dir / "manifest.json").read_text())["items"]
    for item in items:
        bgr = cv2.imread(str(roads_dir / item["image"]), cv2.IMREAD_COLOR)
        frame = decode_frame(cv2.imencode(".jpg", bgr)[1].tobytes())
        seg = working_frame(frame).seg
        palette = np.rint(seg.means).clip(0, 255).astype(np.uint8)
        _same(seg.labels, palette)


def _otsu_all_bins(h):
    """The scan of all 256 candidates that ``otsu_threshold`` ran before it went over occupied bins only."""
    total, levels = int(h.sum()), np.arange(h.size, dtype=np.int64)
    if np.count_nonzero(h) == 1:
        return int(np.flatnonzero(h)[0])
    n1, s1 = np.cumsum(h), np.cumsum(h * levels)
    n2, s2 = total - n1, int(s1[-1]) - s1
    valid = (n1 > 0) & (n2 > 0)
    d = (s1 * n2 - s2 * n1).astype(np.float64)
    denom = n1.astype(np.float64) * n2.astype(np.float64)
    return int(np.argmax(np.where(valid, d * d / np.where(valid, denom, 1.0), -1.0)))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), occupied=st.integers(1, 256), top=st.sampled_from([1, 2, 5, 7500]))
def test_otsu_over_occupied_bins_is_the_scan_of_all_bins(seed, occupied, top):
    rng = np.random.default_rng(seed)
    h = np.zeros(256, np.int64)  # small counts (top 1-2) make exact ties between candidates common
    h[rng.choice(256, occupied, replace=False)] = rng.integers(1, top + 1, occupied)
    assert otsu_of_counts(h) == _otsu_all_bins(h) == otsu_threshold(h)
    for a, b in ((0, 255), (10, 20), (100, 101)):  # two equal spikes: every T between them ties
        two = np.zeros(256, np.int64)
        two[[a, b]] = 5
        assert otsu_of_counts(two) == _otsu_all_bins(two) == a
