"""End to end: `scmr segment`, `scmr eval` and `scmr bench pipeline` on the shared data."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from scmr_mesh.cli import main
from scmr_mesh.imaging import decode_image


def test_segment_writes_pictures_and_reports_bad_inputs(roads_dir, tmp_path, capsys):
    good = sorted((roads_dir / "images").glob("*"))[:1] + sorted((roads_dir / "images").glob("orfd*"))[:1]
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    out = tmp_path / "out"
    argv = ["segment", str(good[0]), str(bad), str(tmp_path / "missing.jpg"), str(good[1])]
    argv += ["--synthetic", "tunnel:2", "--out", str(out), "--stages"]
    assert main(argv) == 1  # two bad inputs, the others still processed
    err = capsys.readouterr().err
    assert err.count("scmr: error:") == 2
    assert "broken.png" in err and "missing.jpg" in err and "Traceback" not in err
    for stem in [good[0].stem, good[1].stem, "tunnel_2"]:
        for kind in ("mask", "rg", "overlay", "srm", "otsu", "hist", "edges"):
            assert (out / f"{stem}.{kind}.png").is_file(), (stem, kind)
        mask = decode_image((out / f"{stem}.mask.png").read_bytes())
        assert mask.shape == (225, 300, 3) and set(np.unique(mask)) <= {0, 255}
        rg = decode_image((out / f"{stem}.rg.png").read_bytes())
        drivable = mask[..., 0] == 255
        assert np.all(rg[drivable] == [0, 255, 0]) and np.all(rg[~drivable] == [255, 0, 0])
    assert not list(out.glob("broken*"))


def test_segment_all_good_exits_zero_and_thesis_mode(tmp_path):
    assert main(["segment", "--synthetic", "desert:1", "--mode", "thesis", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "desert_1.mask.png").is_file() and not (tmp_path / "desert_1.srm.png").exists()


@pytest.mark.parametrize(
    "argv, match",
    [
        (["segment", "--out", "{tmp}"], "no input"),
        (["segment", "--synthetic", "moon", "--out", "{tmp}"], "unknown kind 'moon'"),
        (["segment", "--synthetic", "tunnel:x", "--out", "{tmp}"], "seed must be an integer"),
        (["eval", "{tmp}"], "no manifest.json"),
        (["eval", "{tmp}/nope"], "no such file or folder"),
    ],
)
def test_command_errors_are_one_line(argv, match, tmp_path, capsys):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("scmr: error:") and match in err[-1]


def test_eval_on_the_shared_data(roads_dir, tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert main(["eval", str(roads_dir), "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "bottom_half" in table and "thesis" in table
    doc = json.loads(out.read_text())
    manifest = json.loads((roads_dir / "manifest.json").read_text())
    assert doc["mode"] == "best"
    assert len(doc["images"]) == len(manifest["items"])
    for row in doc["images"]:
        assert {"image", "dataset", "iou", "f1", "precision", "recall"} <= set(row)
        assert all(0.0 <= row[k] <= 1.0 for k in ("iou", "f1", "precision", "recall"))
        assert row["iou"] <= row["f1"] + 1e-12  # IoU <= F1 always
    assert doc["mean"]["iou"] == pytest.approx(np.mean([r["iou"] for r in doc["images"]]))
    assert set(doc["per_dataset"]) == {it["dataset"] for it in manifest["items"]}
    assert sum(v["n"] for v in doc["per_dataset"].values()) == len(doc["images"])
    assert set(doc["baselines"]) == {"bottom_half", "thesis"}
    assert 0.0 <= doc["baselines"]["bottom_half"]["iou"] <= 1.0


def _write_manifest(folder, items):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(json.dumps({"format": "scmr-roads-manifest/1", "items": items}))


def test_eval_rgb_masks_ignore_values_and_a_perfect_score(tmp_path, roads_dir):
    """A manifest whose 'mask' is the pipeline's own output scores exactly 1.0."""
    from scmr_mesh.imaging import encode_png, load_image, segment_drivable

    img_path = sorted((roads_dir / "images").glob("orfd*"))[0]
    mask = segment_drivable(load_image(img_path)).mask
    rgb_mask = np.zeros(mask.shape + (3,), np.uint8)
    rgb_mask[mask > 0] = (255, 0, 255)
    rgb_mask[:5] = (0, 0, 0)  # ignored rows
    (tmp_path / "m.png").write_bytes(encode_png(rgb_mask))
    _write_manifest(
        tmp_path,
        [{"image": str(img_path), "mask": "m.png", "dataset": "x", "mask_mode": "rgb",
          "road": [[255, 0, 255]], "ignore": [[0, 0, 0]]}],
    )
    from scmr_mesh.imaging.evaluate import evaluate

    res = evaluate(tmp_path, baselines=False)
    assert res["images"][0]["iou"] == pytest.approx(1.0)
    assert res["baselines"] == {}


def test_eval_skips_an_unreadable_item_and_scores_the_rest(tmp_path, roads_dir, capsys):
    """A truncated image is reported and skipped; the good item is still scored; exit 1."""
    from scmr_mesh.imaging import encode_png, load_image, segment_drivable

    img_path = sorted((roads_dir / "images").glob("orfd*"))[0]
    mask = segment_drivable(load_image(img_path)).mask
    (tmp_path / "m.png").write_bytes(encode_png(mask))
    (tmp_path / "broken.png").write_bytes(img_path.read_bytes()[:200])
    _write_manifest(
        tmp_path,
        [{"image": str(img_path), "mask": "m.png", "dataset": "x", "mask_mode": "gray", "road": [255]},
         {"image": "broken.png", "mask": "m.png", "dataset": "x", "mask_mode": "gray", "road": [255]}],
    )
    out = tmp_path / "eval.json"
    assert main(["eval", str(tmp_path), "--json", str(out)]) == 1
    err = capsys.readouterr().err
    assert "skipped broken.png" in err and "Traceback" not in err
    doc = json.loads(out.read_text())
    assert [r["image"] for r in doc["images"]] == [img_path.name]
    assert doc["images"][0]["iou"] == pytest.approx(1.0)
    assert [s["image"] for s in doc["skipped"]] == ["broken.png"]


def _block_where(free: np.ndarray, h: int, w: int, rows: range, margin: int = 8) -> tuple[int, int]:
    """The top-left corner of the first h x w block wholly inside ``free`` whose top row is in
    ``rows``, ``margin`` px from the frame's edge."""
    H, W = free.shape
    for y in rows:
        for x in range(margin, W - w - margin):
            if margin <= y <= H - h - margin and free[y:y + h, x:x + w].all():
                return y, x
    raise AssertionError("no such block")


def test_eval_reports_obstacles_painted_drivable(tmp_path, roads_dir, capsys):
    """A "person" block wholly inside the predicted road is all green, a "vehicle" block wholly
    outside none; counted on the pixels 2 px inside each label; the bottom-half baseline alike."""
    from scmr_mesh.imaging import encode_png, load_image, segment_drivable
    from scmr_mesh.imaging.evaluate import OBSTACLE_MARGIN

    img_path = sorted((roads_dir / "images").glob("orfd*"))[0]
    pred = segment_drivable(load_image(img_path)).mask > 0
    truth = np.where(pred, 3, 0).astype(np.uint8)
    # both blocks straddle row 112, where the bottom-half baseline starts: its counts are partial
    py, px = _block_where(pred, 12, 10, range(103, 110))
    vy, vx = _block_where(~pred, 14, 11, range(101, 110))
    truth[py:py + 12, px:px + 10] = 9
    truth[vy:vy + 14, vx:vx + 11] = 8
    (tmp_path / "m.png").write_bytes(encode_png(truth))
    item = {"image": str(img_path), "mask": "m.png", "mask_mode": "gray", "road": [3]}
    _write_manifest(tmp_path / "own", [{**item, "mask": str(tmp_path / "m.png"), "dataset": "x",
                                        "obstacles": {"person": [9], "vehicle": [8]}}])
    _write_manifest(tmp_path / "known", [{**item, "mask": str(tmp_path / "m.png"), "dataset": "camvid"}])
    _write_manifest(tmp_path / "off", [{**item, "mask": str(tmp_path / "m.png"), "dataset": "camvid", "obstacles": {}}])

    m = OBSTACLE_MARGIN
    person_inner = (12 - 2 * m) * (10 - 2 * m)
    vehicle_inner = (14 - 2 * m) * (11 - 2 * m)
    rows = np.arange(225)
    half = lambda y0, hh: int(np.count_nonzero(rows[y0 + m:y0 + hh - m] >= 112))  # noqa: E731
    assert 0 < half(py, 12) < 12 - 2 * m and 0 < half(vy, 14) < 14 - 2 * m
    out = tmp_path / "eval.json"
    for folder in ("own", "known"):
        assert main(["eval", str(tmp_path / folder), "--json", str(out)]) == 0
        doc = json.loads(out.read_text())
        ds = "x" if folder == "own" else "camvid"
        best = doc["obstacles"]["best"][ds]
        assert best["person"] == {"labelled": 120, "labelled_frames": 1, "inner": person_inner,
                                  "green": person_inner, "share": 1.0, "frames": 1, "hit": 1}
        assert best["vehicle"] == {"labelled": 154, "labelled_frames": 1, "inner": vehicle_inner,
                                   "green": 0, "share": 0.0, "frames": 1, "hit": 0}
        assert doc["images"][0]["obstacles"]["person"] == [120, person_inner, person_inner]
        bottom = doc["obstacles"]["bottom_half"][ds]
        green = {"person": half(py, 12) * (10 - 2 * m), "vehicle": half(vy, 14) * (11 - 2 * m)}
        for c in green:
            assert bottom[c]["green"] == green[c] and bottom[c]["hit"] == int(green[c] >= 10)
        assert doc["obstacles"]["thesis"][ds]["person"]["inner"] == person_inner
        table = capsys.readouterr().out
        assert "obstacles painted drivable" in table
        assert re.search(rf"^{ds}\s+person\s+1\.000 \(\s*1/\s*1\)", table, re.M)
    assert set(best) == {"person", "cyclist", "vehicle", "pole"}   # camvid's classes; none shows a cyclist
    assert best["cyclist"]["frames"] == 0
    assert main(["eval", str(tmp_path / "off"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["obstacles"]["best"] == {}
    assert "obstacles painted drivable" not in capsys.readouterr().out


def test_obstacle_green_leaves_the_label_edge_and_keeps_the_frame_edge():
    """Pixels within OBSTACLE_MARGIN of the label's edge are not counted; the frame's edge is not a
    label edge (a car cut by the frame keeps its pixels there); ignored pixels are left out."""
    from scmr_mesh.imaging.evaluate import OBSTACLE_MARGIN, obstacle_green

    m = OBSTACLE_MARGIN
    car = np.zeros((40, 50), bool)
    car[30:, 10:30] = True                  # cut by the bottom edge
    pred = np.full((40, 50), 255, np.uint8)
    assert obstacle_green(pred, car) == ((10 - m) * (20 - 2 * m),) * 2
    valid = np.ones((40, 50), bool)
    valid[38:] = False
    assert obstacle_green(np.zeros_like(pred), car, valid) == ((8 - m) * (20 - 2 * m), 0)
    thin = np.zeros((40, 50), bool)
    thin[5:35, 20:20 + 2 * m] = True        # narrower than the margin's two sides: nothing inside
    assert obstacle_green(pred, thin) == (0, 0)
    notched = np.zeros((40, 50), bool)
    notched[5:15, 5:15] = True
    notched[5, 5] = False                   # the margin is square: the inner pixel diagonal to it goes too
    assert obstacle_green(pred, notched) == ((10 - 2 * m) ** 2 - 1,) * 2


@pytest.mark.parametrize(
    "text, match",
    [
        ("{not json", "not valid JSON"),
        ('{"items": []}', "non-empty 'items'"),
        ('{"items": [{"image": "a.png"}]}', "missing field 'mask'"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "mask_mode": "hsv"}]}', "mask_mode"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "obstacles": [9]}]}', "bad 'obstacles'"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "obstacles": {"person": [[9, 9, 9]]}}]}',
         "bad 'obstacles'"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "obstacles": {"": [9]}}]}', "non-empty string"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "obstacles": {"person": [3]}}]}',
         "lists the road value 3"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [3], "obstacles": {"person": [8.9]}}]}',
         "integers 0-255, got 8.9"),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [[1, 1, 1]], "mask_mode": "rgb", '
         '"obstacles": {"person": [[300, 0, 0]]}}]}', 'got 300); expected e.g. {"person": [[157, 199, 194]]}'),
        ('{"items": [{"image": "a.png", "mask": "b.png", "road": [[-1, 0, 0]], "mask_mode": "rgb"}]}',
         "integers 0-255, got -1"),
    ],
)
def test_eval_invalid_manifest(tmp_path, capsys, text, match):
    (tmp_path / "manifest.json").write_text(text)
    assert main(["eval", str(tmp_path)]) == 1
    assert match in capsys.readouterr().err


def test_bench_pipeline_runs_in_its_own_process(tmp_path):
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [sys.executable, "-m", "scmr_mesh", "bench", "pipeline", "--frames", "4", "--json", str(out)],
        capture_output=True, text=True, timeout=240,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["frames"] == 4
    for key in ("median_ms", "p99_ms"):
        assert {"blur", "srm", "total"} <= set(doc[key])
        assert all(v >= 0 for v in doc[key].values())
    assert doc["p99_ms"]["total"] >= doc["median_ms"]["total"]
    dec = doc["decode"]
    assert set(dec["median_ms"]) == {"png", "jpeg", "bomb 3840x2160", "bomb 7000x7000", "png bomb 3840x2160",
                                     "png 1280x960 (largest accepted)"}
    assert dec["bytes"]["jpeg"] < dec["bytes"]["png"] and dec["bytes"]["bomb 7000x7000"] < 1000
    assert dec["bombs"] == {"bomb 3840x2160": "decoded at reduced scale", "bomb 7000x7000": "refused from its header",
                            "png bomb 3840x2160": "refused from its header",
                            "png 1280x960 (largest accepted)": "decoded in full"}
    assert dec["peak_rss_growth_mb"] < 20
    assert "reference" not in doc
    assert "timed 8/8 runs" in r.stderr
    # libjpeg's warning for each truncated bomb is counted, not printed (it buried the table)
    assert "Corrupt JPEG data" not in r.stderr and dec["libjpeg_warnings"] >= 4
    assert f"libjpeg warned {dec['libjpeg_warnings']} times" in r.stdout


def test_bench_pipeline_reference_needs_dpm_srm(tmp_path):
    """--reference installs nothing: without dpm-srm it says how to get it, in one line."""
    (tmp_path / "dpm_srm.py").write_text("raise ImportError('dpm_srm hidden by the test')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "bench", "pipeline", "--frames", "2", "--reference"],
                       capture_output=True, text=True, timeout=240, env=env)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("scmr: error")]
    assert len(lines) == 1 and "pip install 'scmr-mesh[bench]'" in lines[0], r.stderr


def test_bench_pipeline_reference_ratios(tmp_path):
    pytest.importorskip("dpm_srm", reason="the bench extra (pip install 'scmr-mesh[bench]') is not installed")
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [sys.executable, "-m", "scmr_mesh", "bench", "pipeline", "--frames", "3", "--reference", "--json", str(out)],
        capture_output=True, text=True, timeout=240,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    ref = doc["reference"]
    assert ref["package"] == "dpm-srm" and ref["srm_median_ms"] > 0
    ratios = doc["ratios"]
    assert ratios["total_over_reference_srm"] == pytest.approx(doc["median_ms"]["total"] / ref["srm_median_ms"], rel=0.01)
    assert ratios["srm_over_reference_srm"] == pytest.approx(doc["median_ms"]["srm"] / ref["srm_median_ms"], rel=0.01)
    assert ratios["total_interleaved_over_reference_srm"] == pytest.approx(
        ref["ours_total_interleaved_median_ms"] / ref["srm_median_ms"], rel=0.01)
    assert ratios["total_over_reference_srm_paired"] > 0
    assert "ours / reference" in r.stdout
    verdict = "met" if ratios["total_over_reference_srm_paired"] <= 0.5 else "not met"
    assert f"the total target (<= 0.5) is {verdict} in this run" in r.stdout


def test_bench_decode_pass_passes_on_what_else_reaches_stderr_even_when_it_fails(monkeypatch, capfd):
    """libjpeg's bomb warnings are collected from fd 2; anything else written there comes out, also
    when the pass raises (a review found it lost then)."""
    from scmr_mesh.bench import pipeline as bp
    from scmr_mesh.imaging import codec

    def decode(data, **kw):
        if kw:   # a bomb: the capture is on
            os.write(2, b"Corrupt JPEG data: premature end of data segment\n")
            os.write(2, b"libpng error: something the user must see\n")
            raise RuntimeError("boom")
        return np.zeros((225, 300, 3), np.uint8)

    monkeypatch.setattr(codec, "decode_frame", decode)
    src = [("x", codec.encode_png(np.zeros((8, 8, 3), np.uint8)))]
    with pytest.raises(RuntimeError, match="boom"):
        bp._decode_pass(src, 1, None, 1)
    err = capfd.readouterr().err
    assert "libpng error: something the user must see" in err and "Corrupt JPEG data" not in err
