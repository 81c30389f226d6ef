"""``area_resize``: OpenCV's ``INTER_AREA`` downscale, faster on fractional factors, same bytes."""

from __future__ import annotations

import json
import threading

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.imaging import codec
from scmr_mesh.imaging.codec import FRAME_HEIGHT, FRAME_WIDTH, area_resize, decode_frame, encode_jpeg
from scmr_mesh.imaging.road_model import WORK_SHAPE


def _opencv(rgb, width, height):
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def test_the_road_frames_resize_to_opencv_s_bytes_at_both_of_a_service_s_steps(roads_dir):
    # what a service does to a robot's frame: 640x480 JPEG decoded at 1/2 (320x240), area-resized
    # to 300x225; then best's working frame 150x112 (225 / 112 is not an integer either)
    items = json.loads((roads_dir / "manifest.json").read_text())["items"]
    assert len(items) >= 60
    wh, ww = WORK_SHAPE
    for item in items:
        bgr = cv2.imread(str(roads_dir / item["image"]), cv2.IMREAD_COLOR)
        jpeg = cv2.imencode(".jpg", cv2.resize(bgr, (640, 480), interpolation=cv2.INTER_AREA))[1]
        half = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_REDUCED_COLOR_2), cv2.COLOR_BGR2RGB)
        assert half.shape == (240, 320, 3)
        frame = area_resize(half, FRAME_WIDTH, FRAME_HEIGHT)
        np.testing.assert_array_equal(frame, _opencv(half, FRAME_WIDTH, FRAME_HEIGHT), err_msg=item["image"])
        np.testing.assert_array_equal(area_resize(frame, ww, wh), _opencv(frame, ww, wh), err_msg=item["image"])
        # and the original sizes (1242x375, 1920x1080, ...) straight to the frame, as decode_frame does
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(area_resize(rgb, FRAME_WIDTH, FRAME_HEIGHT),
                                      _opencv(rgb, FRAME_WIDTH, FRAME_HEIGHT), err_msg=item["image"])


def test_decode_frame_of_a_640x480_jpeg_takes_the_kernel_and_matches_opencv(monkeypatch):
    rgb = np.random.default_rng(3).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    data = encode_jpeg(rgb, quality=90)
    calls = []
    real = codec._area_buffers
    monkeypatch.setattr(codec, "_area_buffers", lambda *a: calls.append(a) or real(*a))
    frame = decode_frame(data)
    assert calls == [(240, 320, 3, FRAME_WIDTH)]  # the kernel ran, not OpenCV
    half = cv2.cvtColor(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_COLOR_2), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(frame, _opencv(half, FRAME_WIDTH, FRAME_HEIGHT))


@settings(max_examples=150)
@given(h=st.integers(1, 160), w=st.integers(1, 160), fy=st.floats(0.2, 1.0), fx=st.floats(0.2, 1.0),
       seed=st.integers(0, 2**32 - 1), flat=st.booleans())
def test_any_size_and_any_factor_gives_opencv_s_bytes(h, w, fy, fx, seed, flat):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    if flat:  # large flat areas: sums that land on .5 exactly, where rounding differs if anything does
        rgb[:, : w // 2] = rng.integers(0, 256, 3, dtype=np.uint8)
    width, height = max(1, round(w * fx)), max(1, round(h * fy))
    out = area_resize(rgb, width, height)
    np.testing.assert_array_equal(out, _opencv(rgb, width, height))
    assert out.shape == (height, width, 3) and out.dtype == np.uint8


def test_what_the_kernel_does_not_take_is_opencv_s_own_result():
    rgb = np.random.default_rng(1).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    grey = rgb[:, :, :1].copy()
    cases = [
        (rgb, 640, 480),          # enlargement: OpenCV interpolates linearly
        (rgb, 160, 120),          # integer factors: OpenCV's fast path
        (rgb, 100, 70),           # a factor of 3 or more: OpenCV is as fast
        (grey, 300, 225),         # one channel: OpenCV returns (H, W)
        (rgb[:, ::-1], 300, 225),  # a strided view: copied, then the kernel
    ]
    for img, width, height in cases:
        out, ref = area_resize(img, width, height), _opencv(np.ascontiguousarray(img), width, height)
        assert out.shape == ref.shape
        np.testing.assert_array_equal(out, ref)


def test_threads_resizing_different_sizes_at_once_keep_their_own_scratch_arrays():
    rng = np.random.default_rng(7)
    jobs = [(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), ow, oh)
            for h, w, ow, oh in ((240, 320, 300, 225), (225, 300, 150, 112), (100, 130, 77, 61), (37, 50, 30, 20),
                                         (61, 80, 45, 41))]
    refs = [_opencv(img, ow, oh) for img, ow, oh in jobs]
    bad: list[str] = []
    start = threading.Barrier(len(jobs) * 2)

    def work(k):
        img, ow, oh = jobs[k % len(jobs)]
        start.wait()
        for _ in range(40):
            # every thread goes through all five sizes, one more than the per-thread cache keeps
            for j in range(k, k + len(jobs)):
                img, ow, oh = jobs[j % len(jobs)]
                if not np.array_equal(area_resize(img, ow, oh), refs[j % len(jobs)]):
                    bad.append(f"thread {k}, job {j % len(jobs)}")

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(jobs) * 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not bad, bad[:5]
