"""Test inputs for the imaging code (public: the benches and the tests use them).

:func:`jpeg_bomb` makes the decompression bomb of issue #13: a JPEG of a few
hundred bytes whose frame header claims a huge size.  libjpeg decodes it
(with "premature end of data" warnings), so a decoder that trusts the header
allocates and fills the whole claimed image.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np


def jpeg_bomb(width: int, height: int, *, progressive: bool = False) -> bytes:
    """A JPEG of 16x16 noise (~600-750 bytes) whose frame header claims ``width`` x ``height``.

    Parameters
    ----------
    width, height : int
        The size the header claims (1..65535).
    progressive : bool, keyword-only
        Progressive (SOF2) instead of baseline (SOF0).

    Returns
    -------
    jpeg : bytes

    Examples
    --------
    >>> len(jpeg_bomb(7000, 7000)) < 1000
    True
    """
    img = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    params = [cv2.IMWRITE_JPEG_QUALITY, 50] + ([cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else [])
    jpg = bytearray(cv2.imencode(".jpg", img, params)[1].tobytes())
    i = jpg.index(b"\xff\xc2" if progressive else b"\xff\xc0")
    jpg[i + 5 : i + 9] = struct.pack(">HH", int(height), int(width))
    return bytes(jpg)
