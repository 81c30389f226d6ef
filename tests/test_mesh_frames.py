"""The robot's frame sources: JPEG by default (``--jpeg-quality``), PNG on request."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scmr_mesh.cli import main
from scmr_mesh.errors import InputError
from scmr_mesh.imaging import codec, decode_image, encode_png
from scmr_mesh.mesh import frames, robot
from scmr_mesh.mesh.robot import frames_from_args, image_frames, synthetic_frames


def _picture(h=240, w=320):
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 255 // w, y * 255 // h, np.full_like(x, 90)], axis=2)
    return img.astype(np.uint8)


@pytest.fixture
def folder(tmp_path):
    rgb = _picture()
    (tmp_path / "a.png").write_bytes(encode_png(rgb))
    ok, buf = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 75])
    (tmp_path / "b.jpg").write_bytes(buf.tobytes())
    return tmp_path


def test_default_quality_matches_the_codec():
    assert robot.JPEG_QUALITY == codec.JPEG_QUALITY


def test_png_files_go_out_as_jpeg_and_jpeg_files_unchanged(folder):
    frames = image_frames(folder)
    a, b, a2 = next(frames), next(frames), next(frames)
    assert (a.name, a.encoding) == ("a.png", "jpeg") and a.data[:2] == b"\xff\xd8"
    assert len(a.data) < len((folder / "a.png").read_bytes())
    # the JPEG keeps the picture (quality 90): colours within a few levels
    diff = np.abs(decode_image(a.data).astype(int) - _picture().astype(int))
    assert diff.mean() < 3
    assert (b.encoding, b.data) == ("jpeg", (folder / "b.jpg").read_bytes())
    assert a2 is a  # small folders are encoded once


def test_quality_changes_the_size_and_zero_sends_png(folder):
    low = next(image_frames(folder, jpeg_quality=20)).data
    high = next(image_frames(folder, jpeg_quality=95)).data
    assert len(low) < len(high)
    png = next(image_frames(folder, jpeg_quality=0))
    assert png.encoding == "png" and png.data == (folder / "a.png").read_bytes()


def test_synthetic_frames_are_jpeg_by_default():
    f = next(synthetic_frames("tunnel", seed=3))
    assert f.encoding == "jpeg" and f.data[:2] == b"\xff\xd8" and f.name == "tunnel-3.jpg"
    assert f.rgb.shape == (225, 300, 3)
    p = next(synthetic_frames("tunnel", seed=3, jpeg_quality=0))
    assert p.encoding == "png" and p.data[:4] == b"\x89PNG"
    np.testing.assert_array_equal(decode_image(p.data), f.rgb)


@pytest.mark.parametrize("bad", [-1, 101, 2.5])
def test_bad_quality_is_refused_at_once(folder, bad):
    with pytest.raises(InputError, match="--jpeg-quality"):
        frames_from_args(str(folder), None, jpeg_quality=bad)
    with pytest.raises(InputError, match="--jpeg-quality"):
        frames_from_args(None, "tunnel", jpeg_quality=bad)


def test_robot_cli_refuses_bad_quality_in_one_line(folder, capsys):
    rc = main(["robot", "--insecure", "--id", "r1", "--images", str(folder), "--out", str(folder / "out"),
               "--jpeg-quality", "101"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "--jpeg-quality" in err[0], err


def test_frames_are_made_before_the_robot_sends(folder, monkeypatch):
    """Encoding happens when the source is built (before the robot is ready), not at the first frames."""
    made = []
    real = frames._encode  # the frame sources live in mesh/frames.py
    monkeypatch.setattr(frames, "_encode", lambda rgb, q: (made.append(1), real(rgb, q))[1])
    synthetic_frames("tunnel", seed=1, distinct=3)
    assert len(made) == 3
    made.clear()
    image_frames(folder)
    assert len(made) == 1  # the PNG, re-encoded as JPEG; the JPEG is sent as it is


def test_an_unreadable_image_is_named_at_once(folder, monkeypatch):
    from pathlib import Path

    real = Path.read_bytes

    def read_bytes(self):
        if self.name == "b.jpg":
            raise PermissionError(13, "Permission denied")
        return real(self)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    with pytest.raises(InputError, match=r"cannot read b\.jpg \(Permission denied\); make it readable"):
        image_frames(folder)


def test_a_robot_sends_no_frame_at_or_after_its_duration(tmp_path, monkeypatch):
    """5 Hz for 1 s is 5 frames (at 0, 0.2, ..., 0.8 s), not 6: the one due at 1.0 s is not sent."""
    import itertools
    import time

    r = robot.Robot("r1", tmp_path)
    sent = []
    monkeypatch.setattr(r, "request", lambda seq, frame: (sent.append(time.monotonic()), {"seq": seq})[1])
    t0 = time.monotonic()
    r.run(itertools.repeat(None), rate_hz=5.0, duration_s=1.0)
    # (fewer than 5 only if this machine stalled for a whole period; never a 6th)
    assert 1 <= len(sent) <= 5 and all(s - t0 < 1.0 for s in sent)


def test_a_gated_robot_sends_until_time_0_plus_its_duration():
    from scmr_mesh.mesh.commands import send_window

    s = 1_000_000_000
    assert send_window(10.0, start_ns=5 * s, entered_ns=1, now_ns=5 * s + 300_000_000) == pytest.approx(9.7)
    assert send_window(10.0, start_ns=5 * s, entered_ns=1, now_ns=16 * s) == 0.0  # time 0 + duration has passed
    # a robot started after time 0 (restarted during a scenario, told the time left) keeps its duration
    assert send_window(4.0, start_ns=5 * s, entered_ns=6 * s, now_ns=6 * s + 1) == 4.0
    assert send_window(10.0, start_ns=0, entered_ns=1, now_ns=2) == 10.0  # no time 0 in the file
    assert send_window(None, start_ns=5 * s, entered_ns=1, now_ns=6 * s) is None  # --count, no duration


def test_the_robot_summary_is_one_write():
    """Unbuffered peers share their log with stderr: print()'s separate newline let a log line in."""
    from scmr_mesh.mesh.commands import emit_json_line

    class Recorder:
        def __init__(self):
            self.writes = []

        def write(self, text):
            self.writes.append(text)

        def flush(self):
            pass

    out = Recorder()
    emit_json_line({"robot": "r1", "requests": 3}, out)
    assert out.writes == ['{"robot": "r1", "requests": 3}\n']
