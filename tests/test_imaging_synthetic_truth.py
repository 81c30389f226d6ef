"""``best`` scored against the synthetic scenes' exact truth, per kind (issue 27 item 3).

The demo's overlays are these scenes: road green, verges, walls, rocks and sky red.  A robot
drives where the mask is green, so precision (no green where it cannot drive) is held on every
kind; IoU >= 0.85 is the target of every kind.  One kind is below it today and is asserted
as such (``KNOWN_BELOW``: the floor it holds now, and below the target, so the test says when
it is fixed and when it gets worse); the structured road left that list on 2026-11-29 (0.837 ->
0.855: the boundary cut's chromaticity floor 0.02 -> 0.015 cuts seed 2's gravel verge).  What
the structured road still loses: the road's edges in the lens's dark corners (seeds 1, 6), and a
dash longer than the column fill's gap near the bottom empties the columns it crosses (a red
line down the road: seeds 1, 3, 4, 5, 6; a fill of bright narrow pieces fixed it and was
withdrawn because it painted white posts on the road green, docs/ACCURACY.md).  The kind still below:

* ``desert``: since the open-ground test (sand reaching the horizon under a smooth sky is not a
  leak, :func:`scmr_mesh.imaging.road_model.open_ground`) it is no longer shrunk to the rows
  below ``cap`` (0.639 before), and the bands standing above the horizon go; since the
  open-ground fill keeps the sand beyond a rock (2026-11-29) 0.767 -> 0.781; left: hills that
  SRM merges with the sand stay green, the column fill bridges rocks shorter than its gap, the
  sand in the lens's dark corners and in cast shadows at the sides is lost, and where a shadow
  band crosses the frame (seeds 1, 5, 6: no open ground found) the mask stops at ``cap``
  (``front`` 0.6 found it, 0.876, and was withdrawn: a road-grey wall with a flat top under a
  clear sky passed as open ground too, docs/ACCURACY.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from scmr_mesh.imaging.evaluate import SYNTHETIC_IOU_TARGET as IOU_TARGET
from scmr_mesh.imaging.evaluate import SYNTHETIC_KNOWN_BELOW as KNOWN_BELOW
from scmr_mesh.imaging.evaluate import SYNTHETIC_PRECISION as PRECISION_FLOOR
from scmr_mesh.imaging.evaluate import SYNTHETIC_SEEDS as SEEDS
from scmr_mesh.imaging.evaluate import score, synthetic_floor
from scmr_mesh.imaging.pipeline import segment_drivable
from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene

# The floors live in scmr_mesh.imaging.evaluate (with what each kind measured), where `scmr eval
# --cv` holds every choice to them too; this test holds the defaults to them through
# segment_drivable, independently of the cross-validation's best_masks.


def _scores(kind: str) -> list[dict]:
    out = []
    for seed in SEEDS:
        img, truth = make_scene(kind, seed=seed)
        out.append(score(segment_drivable(img).mask, truth))
    return out


@pytest.mark.parametrize("kind", SCENE_KINDS)
def test_best_against_the_exact_truth_of_each_kind(kind):
    rows = _scores(kind)
    iou = float(np.mean([r["iou"] for r in rows]))
    precision = float(np.mean([r["precision"] for r in rows]))
    assert precision >= PRECISION_FLOOR, f"{kind}: mean precision {precision:.3f} (green where it cannot drive)"
    if kind in KNOWN_BELOW:
        assert iou < IOU_TARGET, f"{kind} now reaches {iou:.3f}: drop it from KNOWN_BELOW"
    assert iou >= synthetic_floor(kind), f"{kind}: mean IoU {iou:.3f} fell below its floor {synthetic_floor(kind)}"


def test_the_scorer_catches_an_over_filled_mask():
    """Control: the bottom half painted green fails the precision floor on the structured road."""
    img, truth = make_scene("structured_road", seed=0)
    half = np.zeros_like(truth)
    half[truth.shape[0] // 2:] = 255
    assert score(half, truth)["precision"] < PRECISION_FLOOR
