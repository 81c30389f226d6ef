"""``best``'s column fill (:func:`scmr_mesh.imaging.pipeline.column_fill`) on analytic candidates."""

from __future__ import annotations

import numpy as np

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
