"""Decoding, encoding and resizing: RGB order, alpha, grey, and every decode error."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from scmr_mesh.errors import ImageDecodeError, InputError
from scmr_mesh.imaging import (
    MAX_PIXELS,
    decode_image,
    encode_png,
    load_image,
    resize_frame,
)


def _rgb(h=7, w=9, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_png_round_trip_keeps_rgb_order():
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # pure red in RGB
    out = decode_image(encode_png(img))
    assert out.dtype == np.uint8 and out.shape == (4, 5, 3)
    np.testing.assert_array_equal(out, img)
    # OpenCV, which works in BGR, must see red in its last channel
    bgr = cv2.imdecode(np.frombuffer(encode_png(img), np.uint8), cv2.IMREAD_COLOR)
    assert bgr[0, 0].tolist() == [0, 0, 200]


def test_jpeg_decodes_to_rgb():
    img = np.zeros((16, 16, 3), np.uint8)
    img[..., 2] = 220  # blue
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = decode_image(buf.tobytes())
    assert out.shape == (16, 16, 3)
    assert out[8, 8, 2] > 200 and out[8, 8, 0] < 20


def test_alpha_dropped_and_grey_expanded():
    bgra = np.zeros((3, 4, 4), np.uint8)
    bgra[..., 0] = 10  # B
    bgra[..., 2] = 30  # R
    bgra[..., 3] = 77  # alpha
    out = decode_image(cv2.imencode(".png", bgra)[1].tobytes())
    assert out.shape == (3, 4, 3) and out[0, 0].tolist() == [30, 0, 10]
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    out = decode_image(cv2.imencode(".png", grey)[1].tobytes())
    assert out.shape == (3, 4, 3)
    np.testing.assert_array_equal(out[..., 1], grey)
    np.testing.assert_array_equal(out[..., 0], out[..., 2])


def test_sixteen_bit_png_scaled_to_eight_bits():
    img16 = np.full((2, 2, 3), 0xABCD, np.uint16)
    out = decode_image(cv2.imencode(".png", img16)[1].tobytes())
    assert out.dtype == np.uint8 and int(out[0, 0, 0]) == 0xAB


def test_raw_rgb_with_shape():
    img = _rgb(3, 5)
    np.testing.assert_array_equal(decode_image(img.tobytes(), shape=(3, 5)), img)
    with pytest.raises(ImageDecodeError, match="must be 45 bytes, got 44"):
        decode_image(img.tobytes()[:-1], shape=(3, 5))
    with pytest.raises(ImageDecodeError, match="empty size"):
        decode_image(b"\x00" * 3, shape=(0, 1))


@pytest.mark.parametrize(
    "data, match",
    [
        (b"", "empty image data"),
        (b"hello, this is not an image at all", "not a PNG or JPEG"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "truncated PNG"),
        (b"\xff\xd8\xff", "JPEG"),
    ],
)
def test_decode_errors_are_clear(data, match):
    with pytest.raises(ImageDecodeError, match=match):
        decode_image(data)


def test_truncated_png_and_jpeg():
    png = encode_png(_rgb(40, 40))
    for cut in (len(png) // 2, len(png) - 13, 40):
        with pytest.raises(ImageDecodeError, match="truncated|corrupt"):
            decode_image(png[:cut])
    jpg = cv2.imencode(".jpg", _rgb(40, 40))[1].tobytes()
    with pytest.raises(ImageDecodeError, match="truncated|corrupt"):
        decode_image(jpg[: len(jpg) // 2])


def test_corrupt_png_body():
    png = bytearray(encode_png(_rgb(30, 30)))
    png[60:120] = b"\x00" * 60  # smash the IDAT data, keep IHDR and IEND
    with pytest.raises(ImageDecodeError, match="corrupt"):
        decode_image(bytes(png))


def _png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk


def test_absurd_png_header_refused_before_decoding():
    data = _png_header(100_000, 100_000) + b"\x00" * 64 + b"IEND"
    with pytest.raises(ImageDecodeError, match="100000x100000") as exc:
        decode_image(data)
    assert str(MAX_PIXELS) in str(exc.value)


def test_absurd_jpeg_header_refused():
    jpg = bytearray(cv2.imencode(".jpg", _rgb(16, 16))[1].tobytes())
    i = jpg.index(b"\xff\xc0")  # baseline SOF0: FF C0 len(2) precision(1) height(2) width(2)
    jpg[i + 5 : i + 9] = struct.pack(">HH", 60000, 60000)
    with pytest.raises(ImageDecodeError, match="60000x60000"):
        decode_image(bytes(jpg))


def test_load_image_names_the_file(tmp_path):
    with pytest.raises(InputError, match="not found: .*missing.png"):
        load_image(tmp_path / "missing.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(ImageDecodeError, match="bad.png: not a PNG"):
        load_image(bad)
    with pytest.raises(InputError, match="directory"):
        load_image(tmp_path)


def test_resize_frame():
    out = resize_frame(_rgb(360, 480))
    assert out.shape == (225, 300, 3) and out.dtype == np.uint8
    frame = _rgb(225, 300)
    assert resize_frame(frame) is frame
    flat = np.full((50, 70, 3), 123, np.uint8)
    assert np.all(resize_frame(flat) == 123)  # area interpolation keeps a flat colour exactly
    with pytest.raises(InputError, match="dtype uint8, got float32"):
        resize_frame(np.zeros((5, 5, 3), np.float32))
