"""``scmr demo`` helpers: pictures from hand-made records, safe replacement of --out. ~2 s."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scmr_mesh.errors import InputError
from scmr_mesh.fleet import RUN_MARKER
from scmr_mesh.fleet.demo import (
    TIER_BGR,
    _clear_previous,
    render_overlays,
    render_timeline,
)

T0 = 1_700_000_000_000_000_000
S = 1_000_000_000


def _records(out):
    recs = []
    for i in range(30):
        tier = "cloud" if i < 10 or i >= 20 else "leader"
        sent = T0 + i * S // 5
        recs.append({"robot": "r1", "seq": i, "image": f"desert-{i}.png", "sent_unix_ns": sent,
                     "received_unix_ns": sent + 20_000_000, "tor_ms": 20.0, "ok": True, "tier": tier})
        mask = np.zeros((225, 300), np.uint8)
        mask[150:] = 255  # bottom is drivable
        (out / "robots" / "r1" / "inbox").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / "robots" / "r1" / "inbox" / f"{i}.mask.png"), mask)
    recs.append({"robot": "r1", "seq": 99, "sent_unix_ns": T0 + 3 * S, "received_unix_ns": None,
                 "tor_ms": None, "ok": False, "tier": None})
    return recs


def test_pictures(tmp_path):
    recs = _records(tmp_path)
    report = {"started_unix_ns": T0, "duration_s": 6.0,
              "faults": [{"kind": "crash", "target": "cloud0", "start_unix_ns": T0 + 2 * S - S // 10,
                          "end_unix_ns": T0 + 4 * S - S // 10}]}
    render_timeline(recs, report, tmp_path / "pics" / "timeline.png")
    img = cv2.imread(str(tmp_path / "pics" / "timeline.png"))
    assert img.shape == (420, 1000, 3)
    for tier in ("cloud", "leader", None):  # dots of each tier and the failed cross are drawn
        assert (np.abs(img.astype(int) - TIER_BGR[tier]).sum(axis=2) < 30).sum() > 20
    assert (np.abs(img.astype(int) - (225, 225, 225)).sum(axis=2) == 0).sum() > 1000  # outage band
    n = render_overlays(recs, report, tmp_path, tmp_path / "pics" / "overlays.png")
    assert n == 3  # before, during, after
    ov = cv2.imread(str(tmp_path / "pics" / "overlays.png"))
    assert ov.shape[1] == 3 * (300 + 8)
    tile = ov[22 + 160: 22 + 220, 4: 300]  # bottom of the first tile: drivable -> greenish
    assert tile[..., 1].mean() > tile[..., 2].mean()
    top = ov[22 + 5: 22 + 100, 4: 300]  # top: not drivable -> reddish
    assert top[..., 2].mean() > top[..., 1].mean()


def test_clear_previous_only_replaces_run_dirs(tmp_path):
    run = tmp_path / "run"
    (run / "robots").mkdir(parents=True)
    (run / RUN_MARKER).write_text("x")
    (run / "ods.sqlite").write_text("x")
    _clear_previous(run)
    assert not run.exists()
    other = tmp_path / "mine"
    other.mkdir()
    (other / "logs").mkdir()  # looks like a run, but has no marker: refuse
    with pytest.raises(InputError, match="not a previous run"):
        _clear_previous(other)
    assert (other / "logs").exists()
    _clear_previous(tmp_path / "missing")  # nothing to do
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="must be a folder"):
        _clear_previous(tmp_path / "f")
