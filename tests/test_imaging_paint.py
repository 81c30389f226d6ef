"""The paint fill (``RoadParams.paint``, :func:`fill_paint`): lane markings left out of the candidate.

Analytic scenes on the 150x112 working frame: a bright line on grey asphalt is filled; a dark
strip, a strip wider than ``paint``, one at the frame's edge and a bright pole that rises above
the road are not; the numba kernel against a plain numpy reading of its definition; and the
whole pipeline on a frame whose long dash near the bottom emptied its columns without the fill.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.errors import InputError
from scmr_mesh.imaging import segment_drivable
from scmr_mesh.imaging._srm_kernels import paint_fill_kernel
from scmr_mesh.imaging.road_model import (
    FEATURE_OFFSET,
    PAINT_BRIGHTER,
    PAINT_MAX_WIDTH,
    WORK_SHAPE,
    RoadParams,
    fill_paint,
)

H, W = WORK_SHAPE
YY, XX = np.mgrid[0:H, 0:W]
TOP = H // 3   # the road's top row


def _road(strip: np.ndarray, colour, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Grey asphalt below TOP (sky above) with ``strip`` painted ``colour``; the candidate is the
    asphalt without the strip (SRM keeps a marking apart and the road model leaves it out)."""
    img = np.empty((H, W, 3))
    img[:] = (140, 170, 210)
    img[TOP:] = (95, 95, 98)
    img[strip] = colour
    img = np.clip(np.rint(img + np.random.default_rng(seed).normal(0, 2, img.shape)), 0, 255).astype(np.uint8)
    cand = np.zeros((H, W), np.uint8)
    cand[TOP:] = 1
    cand[strip] = 0
    return img, cand


def _line(half_width: float, top: int = TOP + 10, bottom: int = H) -> np.ndarray:
    """A slanted line from row ``top`` to ``bottom``, 2 x half_width + 1 px across."""
    return (YY >= top) & (YY < bottom) & (np.abs(XX - (W / 2 + (H - 1 - YY) * 0.15)) <= half_width)


def test_a_bright_line_on_the_road_is_filled():
    line = _line(1)   # 3 px across
    small, cand = _road(line, (235, 235, 230))
    out = fill_paint(cand, small, 3)
    assert out[line].all() and (out[~line] == cand[~line]).all()


@pytest.mark.parametrize("colour", [(60, 60, 62), (100, 100, 103)])
def test_a_strip_no_brighter_than_the_road_stays_out(colour):
    """A dark strip (a crack, a pole's shadow, a tyre) or one of the road's own brightness."""
    line = _line(1)
    small, cand = _road(line, colour)
    assert fill_paint(cand, small, 3) is cand


def test_a_strip_wider_than_paint_stays_out():
    line = _line(2)   # 5 px across
    small, cand = _road(line, (235, 235, 230))
    assert fill_paint(cand, small, 3) is cand
    assert fill_paint(cand, small, 5)[line].all()


def test_a_bright_pole_that_rises_above_the_road_stays_out():
    """Narrow and bright over the road, but its piece reaches the sky: not paint."""
    pole = (np.abs(XX - 40) <= 1) & (YY >= 5) & (YY < H - 20)
    small, cand = _road(pole, (230, 230, 225))
    assert fill_paint(cand, small, 3) is cand


def test_a_strip_at_the_frames_edge_stays_out():
    """Candidate on one side only: nothing says the road goes on beyond it."""
    edge = (XX <= 1) & (YY >= TOP + 5)
    small, cand = _road(edge, (235, 235, 230))
    assert fill_paint(cand, small, 3) is cand


def test_paint_zero_is_off():
    line = _line(1)
    small, cand = _road(line, (235, 235, 230))
    assert fill_paint(cand, small, 0) is cand


def _fill_reference(cand: np.ndarray, small: np.ndarray, width: int, brighter: float) -> np.ndarray:
    """fill_paint's definition in numpy and OpenCV's connected components."""
    lum = np.log(small.astype(np.int64).sum(axis=2) / 3.0 + FEATURE_OFFSET)
    runs = np.zeros(cand.shape, bool)
    for y in range(cand.shape[0]):
        row = cand[y] != 0
        x = 0
        while x < row.size:
            if row[x]:
                x += 1
                continue
            s = x
            while x < row.size and not row[x]:
                x += 1
            if 0 < s and x < row.size and x - s <= width and lum[y, s:x].max() >= max(lum[y, s - 1], lum[y, x]) + brighter:
                runs[y, s:x] = True
    n, comp = cv2.connectedComponents((cand == 0).astype(np.uint8), connectivity=4)
    off = np.zeros(n, bool)
    off[comp[(cand == 0) & ~runs]] = True
    return ((cand != 0) | (runs & ~off[comp])).astype(np.uint8)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), width=st.integers(1, PAINT_MAX_WIDTH), density=st.floats(0.3, 0.95),
       lines=st.integers(0, 6))
def test_the_kernel_agrees_with_numpy(seed, width, density, lines):
    """Random candidates, plus bright vertical strips so that pieces do get filled."""
    rng = np.random.default_rng(seed)
    cand = (rng.random((H, W)) < density).astype(np.uint8)
    small = rng.integers(0, 200, (H, W, 3), dtype=np.uint8)
    for _ in range(lines):
        x = int(rng.integers(1, W - 4))
        y0, y1 = sorted(int(v) for v in rng.integers(0, H, 2))
        wd = int(rng.integers(1, 4))
        cand[y0:y1, x:x + wd] = 0
        cand[y0:y1, x - 1] = 1
        cand[y0:y1, x + wd] = 1
        small[y0:y1, x:x + wd] = 250
    from scmr_mesh.imaging.road_model import _tables

    got, filled = paint_fill_kernel(cand, small, _tables()[1], width, PAINT_BRIGHTER)
    want = _fill_reference(cand, small, width, PAINT_BRIGHTER)
    assert np.array_equal(got, want) and filled == int((want != cand).sum())


def test_a_long_dash_near_the_bottom_no_longer_empties_its_columns():
    """The whole pipeline on a 300x225 frame: a 5 px dash 75 rows tall from the bottom, longer
    than the column fill's gap.  Without the fill its columns were red from the bottom up (a red
    line down the road); with it they are green."""
    rng = np.random.default_rng(0)
    img = np.empty((225, 300, 3))
    img[:] = (140, 170, 210)
    img[100:] = (95, 95, 98)
    yy, xx = np.mgrid[0:225, 0:300]
    dash = (yy >= 150) & (np.abs(xx - (150 + (224 - yy) * 0.15)) <= 2)
    img[dash] = (235, 235, 230)
    img = np.clip(np.rint(img + rng.normal(0, 3, img.shape)), 0, 255).astype(np.uint8)
    off = segment_drivable(img, params=RoadParams(paint=0)).mask > 0
    on = segment_drivable(img).mask > 0
    assert (~off[200:]).all(axis=0).sum() >= 2        # the failure this guards against
    assert on[dash].all() and on[100:].all()
    assert not on[:95].any()                           # and no more: the sky stays red


@pytest.mark.parametrize("bad", [-1, PAINT_MAX_WIDTH + 1, 2.5, True, "3"])
def test_a_bad_paint_width_is_one_line_naming_it(bad):
    with pytest.raises(InputError, match=r"^paint must be an integer width .* got ") as e:
        RoadParams(paint=bad).check()
    assert "\n" not in str(e.value)
