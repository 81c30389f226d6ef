"""``best``'s column fill (:func:`scmr_mesh.imaging.pipeline.column_fill`) on analytic candidates."""

from __future__ import annotations

import numpy as np
import pytest

from scmr_mesh.imaging.pipeline import column_fill

H, W = 60, 40
GAP = 5


def _ground_with_a_rock(rock_rows: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Candidate ground from row 20 down, a rock (not candidate) 8 px wide and ``rock_rows`` tall
    in the middle: the columns above it are ground reached around the rock."""
    c = np.zeros((H, W), np.uint8)
    c[20:] = 1
    rock = np.zeros((H, W), bool)
    rock[35:35 + rock_rows, 16:24] = True
    c[rock] = 0
    return c, rock


def test_a_rock_taller_than_the_gap_stops_its_columns_off_open_ground():
    """The dissertation's rule (Table 3.5): drivable up to the first obstacle along the column."""
    c, rock = _ground_with_a_rock()
    out = column_fill(c, GAP, False) > 0
    assert not out[rock].any() and not out[20:35, 16:24].any()
    assert out[20:, :16].all() and out[20:, 24:].all()


def test_on_open_ground_the_ground_beyond_a_rock_stays():
    c, rock = _ground_with_a_rock()
    out = column_fill(c, GAP, True) > 0
    assert not out[rock].any()             # the rock stays red
    assert out[20:35, 16:24].all()         # the sand beyond it is green
    assert not out[:20].any()              # and nothing above the ground


def test_on_open_ground_short_holes_are_bridged_and_a_bottom_rock_stays_red():
    c = np.zeros((H, W), np.uint8)
    c[20:] = 1
    c[30:33, 5:8] = 0                      # a hole shorter than the gap: bridged
    c[H - 10:, 30:36] = 0                  # a rock at the bottom of the frame: stays red
    out = column_fill(c, GAP, True) > 0
    assert out[30:33, 5:8].all()
    assert not out[H - 10:, 30:36].any() and out[20:H - 10, 30:36].all()


def _road_frame(paint) -> tuple[np.ndarray, np.ndarray]:
    """A 300x225 frame: sky, grey road from row 100, and ``paint(img, yy, xx)`` returning a mask."""
    img = np.empty((225, 300, 3))
    img[:] = (140, 170, 210)
    img[100:] = (95, 95, 98)
    yy, xx = np.mgrid[0:225, 0:300]
    m = paint(img, yy, xx)
    img = np.clip(np.rint(img + np.random.default_rng(0).normal(0, 3, img.shape)), 0, 255).astype(np.uint8)
    return img, m


def _box(img, yy, xx, x0, y0, w, h, colour):
    m = (xx >= x0) & (xx < x0 + w) & (yy >= y0) & (yy < y0 + h)
    img[m] = colour
    return m


def _dark_pole_with_a_highlight(img, yy, xx):
    m = _box(img, yy, xx, 150, 130, 6, 60, (45, 45, 45))
    img[m & (xx < 152)] = (225, 225, 225)
    return m


@pytest.mark.parametrize("paint", [
    lambda img, yy, xx: _box(img, yy, xx, 100, 150, 6, 30, (235, 235, 230)),   # a white bollard
    lambda img, yy, xx: _box(img, yy, xx, 200, 120, 6, 88, (235, 235, 230)),   # a white post
    _dark_pole_with_a_highlight,
], ids=["white bollard", "white post", "dark pole with a highlight"])
def test_a_narrow_post_standing_on_the_road_stays_red(paint):
    """The attacker's scenes of the 2026-11-29 review: narrow objects wholly on the road, taller than
    the column fill's gap.  A fill of bright narrow pieces (to mend lane dashes) painted them all
    green and was withdrawn; any such fill must keep them red."""
    from scmr_mesh.imaging import segment_drivable

    img, post = _road_frame(paint)
    mask = segment_drivable(img).mask > 0
    assert not mask[post].any()
    assert mask[200:, :90].all()     # while the road beside them is green


def test_on_open_ground_a_piece_the_fill_did_not_reach_stays_out():
    """The carried model's candidate and the boundary cut can hold pieces apart from the seed: only
    the candidate joined to what the column fill reached stays beyond a rock."""
    c, rock = _ground_with_a_rock()
    c[20:25, 17:23] = 0                    # cut the ground beyond the rock off at its top ...
    c[20:25, 16] = 0
    c[20:25, 23] = 0
    island = np.zeros((H, W), bool)
    island[8:12, 17:23] = True             # ... and an island of candidate above, apart from it all
    c[island] = 1
    out = column_fill(c, GAP, True) > 0
    assert out[25:35, 17:23].all()         # the ground beyond the rock, joined to the rest
    assert not out[island].any()
