"""Decoding, encoding and resizing of frames (SPEC section 1, step 1).

Every frame in scmr-mesh is an ``(H, W, 3) uint8`` array in **RGB** order.
OpenCV works in BGR; the functions here are the only place that converts, so
callers never have to think about it.

Decoding is defensive: the header is parsed *before* decoding so that a tiny
file that claims to be a huge image (a decompression bomb) is refused cheaply,
and every failure raises :class:`~scmr_mesh.errors.ImageDecodeError` with a
message that says what was received.  Two limits:

* :data:`MAX_PIXELS`: 3840 x 2160 (4K UHD), the largest frame common robot
  cameras send; anything larger is refused from its header.
* :data:`MAX_PROGRESSIVE_PIXELS`: 1920 x 1080 for progressive JPEGs, because
  libjpeg buffers every DCT coefficient of a progressive image (about 3 bytes
  per pixel at 4:2:0) whatever the output scale.  Camera encoders emit
  baseline JPEG.
* :data:`MAX_PNG_FRAME_PIXELS`: 1280 x 960 for PNG frames a service decodes
  (``decode_frame(..., max_png_pixels=...)``, what the workers run): PNG has no
  reduced decode, so a 28 KB PNG of zeros claiming 3840 x 2160 cost 95-159 ms of
  CPU and 24 MB; at 1280 x 960 the worst PNG costs about 14-19 ms and 3.7 MB.
  Robots send JPEG (a PNG from ``--images`` is re-encoded as JPEG unless
  ``--jpeg-quality 0``); local tools (``scmr segment``) keep the 4K limit.

:func:`decode_frame` is what the services run: it decodes a JPEG at 1/2, 1/4
or 1/8 scale in libjpeg's DCT (OpenCV's ``IMREAD_REDUCED_COLOR_*``) so that the
result is still at least 300x225, then resizes to the 300x225 frame.  A
631-byte JPEG whose header claims 3840x2160 costs about 2 ms and under 1 MB
that way (a 7000x7000 one is refused from its header; before these limits it
cost 0.64 s of CPU and 280 MB).
"""

from __future__ import annotations

import functools
import logging
import math
import struct
import threading
from pathlib import Path

import cv2
import numpy as np

from scmr_mesh.errors import ImageDecodeError, InputError

log = logging.getLogger(__name__)

#: Width and height of the frame every pipeline stage works on (SPEC 1, step 1).
FRAME_WIDTH = 300
FRAME_HEIGHT = 225
FRAME_SHAPE = (FRAME_HEIGHT, FRAME_WIDTH)

#: Largest image (in pixels) the decoders accept: 3840 x 2160 (4K UHD), the
#: largest frame common robot cameras send (the thesis's were 640x480).
MAX_PIXELS = 3840 * 2160
#: Largest progressive JPEG: 1920 x 1080.  libjpeg keeps all DCT coefficients of a
#: progressive image in memory (about 3 bytes per pixel at 4:2:0), even when it
#: decodes at reduced scale; camera encoders emit baseline JPEG.
MAX_PROGRESSIVE_PIXELS = 1920 * 1080
#: Largest PNG frame a service decodes: 1280 x 960.  PNG cannot be decoded at reduced scale,
#: so its cost grows with the claimed size whatever the file size (measured, one core:
#: 3840x2160 of zeros, 28 KB: 95 ms; 1920x1080: 24 ms; 1280x960: 14 ms, 19 ms for noise).
MAX_PNG_FRAME_PIXELS = 1280 * 960
#: Default JPEG quality of frames a robot sends (the thesis's frames were 80-130 KB JPEGs).
JPEG_QUALITY = 90

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_MAGIC = b"\xff\xd8"
# JPEG start-of-frame markers that carry the image size (not DHT/JPG/DAC).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# progressive (and lossless) SOF markers: libjpeg buffers the whole coefficient image
_PROGRESSIVE_SOF = {0xC2, 0xC3, 0xC6, 0xC7, 0xCA, 0xCB, 0xCE, 0xCF}


def _check_size(width: int, height: int, what: str, limit: int = MAX_PIXELS) -> None:
    if width <= 0 or height <= 0:
        raise ImageDecodeError(f"{what} header gives an empty size {width}x{height}; the file is corrupt")
    if width * height > limit:
        raise ImageDecodeError(
            f"{what} header claims {width}x{height} = {width * height} pixels, more than the "
            f"{limit} allowed (cameras send at most 3840x2160); refusing to decode "
            "(downscale the image first)"
        )


def _png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ImageDecodeError(f"truncated PNG: {len(data)} bytes, no complete IHDR header")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _jpeg_size(data: bytes) -> tuple[int, int, int, bool]:
    """Return (width, height, offset after the SOF segment, progressive) of a JPEG."""
    i = 2
    n = len(data)
    while i < n:
        if data[i] != 0xFF:
            raise ImageDecodeError(f"corrupt JPEG: expected a marker at byte {i}, got 0x{data[i]:02x}")
        while i < n and data[i] == 0xFF:  # fill bytes
            i += 1
        if i >= n:
            break
        marker = data[i]
        i += 1
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            continue
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any SOF
            break
        if i + 2 > n:
            break
        (seg_len,) = struct.unpack(">H", data[i : i + 2])
        if marker in _SOF_MARKERS:
            if i + 7 > n:
                break
            height, width = struct.unpack(">HH", data[i + 3 : i + 7])
            return width, height, i + seg_len, marker in _PROGRESSIVE_SOF
        i += seg_len
    raise ImageDecodeError(f"truncated or corrupt JPEG: no frame header in {len(data)} bytes")


def _check_bytes(data) -> bytes:
    if isinstance(data, (bytearray, memoryview)):
        data = bytes(data)
    if not isinstance(data, bytes):
        raise ImageDecodeError(f"image data must be bytes, got {type(data).__name__}")
    if len(data) == 0:
        raise ImageDecodeError("empty image data (0 bytes)")
    return data


def _raw(data: bytes, shape) -> np.ndarray:
    try:
        height, width = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise ImageDecodeError(f"shape must be (height, width), got {shape!r}") from None
    _check_size(width, height, "raw RGB")
    expected = height * width * 3
    if len(data) != expected:
        raise ImageDecodeError(f"raw RGB data for shape {height}x{width} must be {expected} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3).copy()


def _sniff(data: bytes) -> tuple[str, int, int]:
    """Kind ("PNG"/"JPEG") and header size of encoded bytes, after the size and truncation checks."""
    if data.startswith(_PNG_MAGIC):
        width, height = _png_size(data)
        _check_size(width, height, "PNG")
        if data.rfind(b"IEND") < 0:
            raise ImageDecodeError(f"truncated PNG: {len(data)} bytes and no IEND chunk")
        return "PNG", width, height
    if data.startswith(_JPEG_MAGIC):
        width, height, after_sof, progressive = _jpeg_size(data)
        _check_size(width, height, "JPEG")
        if progressive:
            _check_size(width, height, "progressive JPEG", MAX_PROGRESSIVE_PIXELS)
        if data.rfind(b"\xff\xd9", after_sof) < 0:
            raise ImageDecodeError(f"truncated JPEG: {len(data)} bytes and no end-of-image marker")
        return "JPEG", width, height
    head = data[:8].hex()
    raise ImageDecodeError(
        f"not a PNG or JPEG image (first bytes {head}); pass PNG/JPEG, or raw RGB with shape=(H, W)"
    )


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(kind, width, height)`` of PNG/JPEG bytes from their header, without decoding the pixels.

    The checks :func:`decode_image` makes before it decodes: PNG or JPEG, a size within
    :data:`MAX_PIXELS` (and :data:`MAX_PROGRESSIVE_PIXELS` for a progressive JPEG), the end
    marker present (IEND / EOI).  A body corrupt past its header is not detected here.

    Raises
    ------
    ImageDecodeError
        As :func:`decode_image` does for the same checks.

    Examples
    --------
    >>> image_size(encode_png(np.zeros((2, 3), np.uint8)))
    ('PNG', 3, 2)
    """
    return _sniff(_check_bytes(data))


def _imdecode(data: bytes, flags: int, kind: str) -> np.ndarray:
    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, flags)
    except cv2.error as exc:  # pragma: no cover - OpenCV usually returns None
        raise ImageDecodeError(f"corrupt {kind} ({len(data)} bytes): {exc}") from None
    if img is None or img.size == 0:
        raise ImageDecodeError(f"corrupt or truncated {kind} ({len(data)} bytes): OpenCV could not decode it")
    return img


def decode_image(data: bytes, *, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Decode PNG/JPEG bytes (or raw RGB bytes) to an RGB image at full size.

    Services use :func:`decode_frame`, which decodes JPEGs at reduced scale;
    this function is for callers that need every source pixel.

    Parameters
    ----------
    data : bytes
        An encoded PNG or JPEG, or raw ``H * W * 3`` RGB bytes when ``shape``
        is given.
    shape : tuple of int, optional
        ``(H, W)`` of raw RGB bytes.  Leave out for PNG/JPEG.

    Returns
    -------
    rgb : (H, W, 3) uint8
        RGB order.  Alpha is dropped, grey images get three equal channels,
        16-bit images are scaled to 8 bits.  EXIF orientation is ignored.

    Raises
    ------
    ImageDecodeError
        Empty, truncated, not PNG/JPEG, corrupt, larger than
        :data:`MAX_PIXELS` (or a progressive JPEG larger than
        :data:`MAX_PROGRESSIVE_PIXELS`), checked from the header before decoding.

    Examples
    --------
    >>> rgb = decode_image(bytes(2 * 3 * 3), shape=(2, 3))
    >>> rgb.shape, rgb.dtype.name
    ((2, 3, 3), 'uint8')
    """
    data = _check_bytes(data)
    if shape is not None:
        return _raw(data, shape)
    kind, _, _ = _sniff(data)
    return _to_rgb(_imdecode(data, cv2.IMREAD_UNCHANGED, kind))


#: OpenCV flags decoding a JPEG at 1/factor scale in libjpeg's DCT (BGR, EXIF orientation ignored).
_REDUCED = {
    2: cv2.IMREAD_REDUCED_COLOR_2 | cv2.IMREAD_IGNORE_ORIENTATION,
    4: cv2.IMREAD_REDUCED_COLOR_4 | cv2.IMREAD_IGNORE_ORIENTATION,
    8: cv2.IMREAD_REDUCED_COLOR_8 | cv2.IMREAD_IGNORE_ORIENTATION,
}


def reduction_factor(width: int, height: int) -> int:
    """The largest JPEG DCT scale 1/r (r in 1, 2, 4, 8) that keeps the image at least 300x225.

    Examples
    --------
    >>> reduction_factor(640, 480), reduction_factor(1920, 1200), reduction_factor(1242, 375)
    (2, 4, 1)
    """
    for r in (8, 4, 2):
        if -(-width // r) >= FRAME_WIDTH and -(-height // r) >= FRAME_HEIGHT:
            return r
    return 1


def decode_frame(data: bytes, *, shape: tuple[int, int] | None = None,
                 max_png_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Decode PNG/JPEG bytes (or raw RGB bytes) straight to the 300x225 pipeline frame.

    A JPEG is decoded at the smallest DCT scale (1/2, 1/4 or 1/8, OpenCV's
    ``IMREAD_REDUCED_COLOR_*``) that is still at least 300x225, so a large
    frame (or a decompression bomb) never materialises at full size; the
    result is then resized with area interpolation.  PNG and raw frames are
    decoded in full (PNG has no reduced decode) and resized.

    Parameters
    ----------
    data : bytes
        An encoded PNG or JPEG, or raw ``H * W * 3`` RGB bytes when ``shape``
        is given.
    shape : tuple of int, optional
        ``(H, W)`` of raw RGB bytes.
    max_png_pixels : int, keyword-only
        Largest PNG accepted (the services pass :data:`MAX_PNG_FRAME_PIXELS`).

    Returns
    -------
    frame : (225, 300, 3) uint8
        RGB order.

    Raises
    ------
    ImageDecodeError
        As :func:`decode_image`.

    Examples
    --------
    >>> decode_frame(bytes(2 * 3 * 3), shape=(2, 3)).shape
    (225, 300, 3)
    """
    data = _check_bytes(data)
    if shape is not None:
        return resize_frame(_raw(data, shape))
    kind, width, height = _sniff(data)
    if kind == "PNG" and width * height > max_png_pixels:
        raise ImageDecodeError(
            f"PNG header claims {width}x{height} = {width * height} pixels, more than the {max_png_pixels} a "
            "service decodes from PNG (PNG has no reduced-scale decode, so a small PNG claiming a large frame "
            "is a decompression bomb); send the frame as JPEG, or downscale it")
    r = reduction_factor(width, height) if kind == "JPEG" else 1
    if r == 1:
        return resize_frame(_to_rgb(_imdecode(data, cv2.IMREAD_UNCHANGED, kind)))
    return resize_frame(_to_rgb(_imdecode(data, _REDUCED[r], kind)))


def _to_rgb(img: np.ndarray) -> np.ndarray:
    """OpenCV's decoded array (grey / BGR / BGRA, 8 or 16 bit) -> RGB uint8."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    channels = img.shape[2]
    if channels == 1:
        return cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2RGB)
    if channels == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _load(path: str | Path, decode) -> np.ndarray:
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise InputError(f"image file not found: {p}") from None
    except IsADirectoryError:
        raise InputError(f"expected an image file, got a directory: {p}") from None
    except OSError as exc:
        raise InputError(f"cannot read image file {p}: {exc.strerror or exc}") from None
    try:
        return decode(data)
    except ImageDecodeError as exc:
        raise ImageDecodeError(f"{p}: {exc}") from None


def load_image(path: str | Path) -> np.ndarray:
    """Read a PNG/JPEG file as an RGB image at full size (:func:`decode_image`).

    Parameters
    ----------
    path : str or Path
        The image file.

    Returns
    -------
    rgb : (H, W, 3) uint8

    Raises
    ------
    InputError
        The file is missing or unreadable.
    ImageDecodeError
        The bytes are not an acceptable image; the message names the file.
    """
    return _load(path, decode_image)


def load_frame(path: str | Path) -> np.ndarray:
    """Read a PNG/JPEG file straight to the (225, 300, 3) frame (:func:`decode_frame`).

    This is the decode the services run, so ``scmr segment`` and ``scmr eval``
    see what a robot's frame turns into.

    Raises
    ------
    InputError, ImageDecodeError
        As :func:`load_image`.
    """
    return _load(path, decode_frame)


def as_rgb(image: np.ndarray, *, name: str = "image") -> np.ndarray:
    """Validate an array as an RGB frame, converting grey/RGBA where that is unambiguous.

    Parameters
    ----------
    image : (H, W, 3) uint8, also (H, W) or (H, W, 1) grey and (H, W, 4) RGBA
        The frame.

    Returns
    -------
    rgb : (H, W, 3) uint8, C-contiguous

    Raises
    ------
    InputError
        Wrong type, dtype, number of dimensions/channels, or an empty array.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(
            f"{name} must have dtype uint8, got {image.dtype}; convert with "
            "np.clip(a, 0, 255).astype(np.uint8)"
        )
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 3, 4):
        raise InputError(f"{name} must have shape (H, W, 3), got {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise InputError(f"{name} is empty: shape {image.shape}")
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    elif image.shape[2] == 4:
        image = image[:, :, :3]
    return np.ascontiguousarray(image)


def resize_frame(rgb: np.ndarray) -> np.ndarray:
    """Resize a frame to the pipeline's 300x225 with area interpolation.

    Parameters
    ----------
    rgb : (H, W, 3) uint8

    Returns
    -------
    frame : (225, 300, 3) uint8
        The input itself (no copy) when it already has that size.
    """
    rgb = as_rgb(rgb, name="rgb")
    if rgb.shape[:2] == FRAME_SHAPE:
        return rgb
    return area_resize(rgb, FRAME_WIDTH, FRAME_HEIGHT)


@functools.lru_cache(maxsize=64)
def _area_table(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One axis of OpenCV's ``INTER_AREA`` downscale (``computeResizeAreaTab``) as CSR arrays.

    Output ``d`` covers source ``[d * s, (d + 1) * s)``, ``s = n_in / n_out``; each source
    pixel weighs its overlap over the cell's width.  Returns ``(ptr, idx, w)``: int64, int64,
    float32 (OpenCV's own precision for 8-bit images).
    """
    scale = 1.0 / (n_out / n_in)  # as OpenCV: 1 / inv_scale, in double
    ptr, idx, w = [0], [], []
    for d in range(n_out):
        f1 = d * scale
        f2 = f1 + scale
        cell = min(scale, n_in - f1)
        s1, s2 = math.ceil(f1), math.floor(f2)
        s2 = min(s2, n_in - 1)
        s1 = min(s1, s2)
        if s1 - f1 > 1e-3:
            idx.append(s1 - 1)
            w.append((s1 - f1) / cell)
        for s in range(s1, s2):
            idx.append(s)
            w.append(1.0 / cell)
        if f2 - s2 > 1e-3:
            idx.append(s2)
            w.append(min(min(f2 - s2, 1.0), cell) / cell)
        ptr.append(len(idx))
    # cached and shared by every call: the kernels only read them
    return np.array(ptr, np.int64), np.array(idx, np.int64), np.array(w, np.float32)


def area_resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """``cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)``, faster where OpenCV is slow.

    OpenCV's area resampling is fast only for integer factors; a fractional downscale such
    as the 320x240 of a JPEG decoded at 1/2 to the pipeline's 300x225 takes its generic path
    (about 1 ms on one core of the 2-core development box).  A fractional downscale of a
    3-channel image by less than 3 runs here instead: OpenCV's weights and float32 sums in
    its order, over whole rows (across on the transposed image, then down), so it
    vectorizes, and the same bytes as OpenCV (``tests/test_imaging_area.py`` compares them on
    the road frames and on random sizes).  In a service's decode of a 640x480 JPEG it takes
    about 0.4 ms off 3.0 (``scmr bench pipeline``, docs/BENCHMARKS.md).  An exact 2:1 across
    with a fractional down on a small image (the 300x225 frame to best's 150x112) runs in one
    pass instead, with row-sized buffers: the two-pass kernel's 1 MB of scratch arrays falls
    out of the cache between frames there.  Anything else goes to OpenCV.

    Parameters
    ----------
    rgb : (H, W, C) uint8
    width, height : int
        Output size.

    Returns
    -------
    (height, width, C) uint8
    """
    if rgb.ndim != 3 or rgb.dtype != np.uint8 or rgb.shape[2] != 3:
        return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    h, w = rgb.shape[:2]
    if (not (0 < width <= w and 0 < height <= h)
            or (w % width == 0 and h % height == 0) or w >= 3 * width or h >= 3 * height):
        return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    if w == 2 * width and h * width * 3 <= _HALF_MAX_VALUES:
        # an exact 2:1 across and a fractional down (best's 300x225 -> 150x112): one pass, row buffers
        from scmr_mesh.imaging._aot import area_half_kernel

        src = np.ascontiguousarray(rgb)
        if not src.flags.writeable:  # the kernel's one signature takes writeable arrays (no second JIT)
            src = src.copy()
        out = area_half_kernel(src.reshape(h, w * 3), *_area_table(h, height),
                               np.empty((height, width * 3), np.uint8))
        return out.reshape(height, width, 3)
    from scmr_mesh.imaging._aot import area_round_kernel, area_rows_kernel

    c = rgb.shape[2]
    cols, across, rows = _area_buffers(h, w, c, width)
    # across: the columns of the transposed image are its rows (cv2.transpose: about 0.04 ms)
    cv2.transpose(np.ascontiguousarray(rgb), dst=cols)
    area_rows_kernel(cols.reshape(w, h * c), *_area_table(w, width), across)
    cv2.transpose(across.reshape(width, h, c), dst=rows)
    out = area_round_kernel(rows.reshape(h, width * c), *_area_table(h, height),
                            np.empty((height, width * c), np.uint8))
    return out.reshape(height, width, c)


#: :func:`area_resize`'s one-pass kernel for an exact 2:1 across takes images up to this many output
#: values per source row times rows (300x225 -> 150x112 is 101,250).  On best's frame it takes
#: 0.19 ms against OpenCV's 0.41 (interleaved, one core of the 2-core development box); on larger
#: images the two-pass kernels, whose inner loops run over whole rows, are at least as fast.
_HALF_MAX_VALUES = 400_000

_area_local = threading.local()
#: Sizes of scratch arrays :func:`area_resize` keeps per thread.
_AREA_SHAPES = 4


def _area_buffers(h: int, w: int, c: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """This thread's scratch arrays for :func:`area_resize` of these sizes, kept for the next call.

    Fresh ones per call (about 2 MB for 320x240 -> 300x225) tripled its time on real frames:
    the allocator hands back new pages to fault in.  A thread that meets frames of several
    sizes (robots with different cameras) keeps the arrays of the last :data:`_AREA_SHAPES`.
    """
    cache = getattr(_area_local, "bufs", None)
    if cache is None:
        cache = _area_local.bufs = {}
    key = (h, w, c, width)
    bufs = cache.get(key)
    if bufs is None:
        if len(cache) >= _AREA_SHAPES:
            cache.pop(next(iter(cache)))
        bufs = cache[key] = (np.empty((w, h, c), np.uint8), np.empty((width, h * c), np.float32),
                             np.empty((h, width, c), np.float32))
    return bufs


def encode_png(array: np.ndarray) -> bytes:
    """Encode an RGB (or grey) uint8 array as PNG bytes, with the colours right.

    Parameters
    ----------
    array : (H, W, 3) or (H, W) uint8
        RGB order (converted to OpenCV's BGR here), or single-channel grey.

    Returns
    -------
    png : bytes
    """
    if not isinstance(array, np.ndarray) or array.dtype != np.uint8:
        raise InputError(f"encode_png needs a uint8 numpy array, got {getattr(array, 'dtype', type(array))}")
    if array.ndim == 3 and array.shape[2] == 3:
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2BGR)
    elif array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    elif array.ndim != 2:
        raise InputError(f"encode_png needs shape (H, W) or (H, W, 3), got {array.shape}")
    ok, buf = cv2.imencode(".png", array)
    if not ok:  # pragma: no cover
        raise InputError(f"OpenCV could not encode an array of shape {array.shape} as PNG")
    return buf.tobytes()


#: A mask's PNG: rows unfiltered and deflate level 1.  OpenCV's default (adaptive filters) took
#: 0.26 ms to decode a service's 300x225 mask and 0.11 ms to encode it; this takes 0.05 and 0.08 ms,
#: for about 150 bytes more (medians over 10 pipeline masks of ../shared/data/roads, 2-core box).
#: The same 8-bit greyscale PNG to every reader; the bridge decodes one per frame (docs/ROS2.md).
MASK_PNG_PARAMS = (cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE, cv2.IMWRITE_PNG_COMPRESSION, 1)


def encode_mask_png(mask: np.ndarray) -> bytes:
    """Encode a (H, W) uint8 mask as an 8-bit greyscale PNG that decodes fast (:data:`MASK_PNG_PARAMS`).

    >>> m = np.zeros((4, 6), np.uint8); m[2:] = 255
    >>> bool((cv2.imdecode(np.frombuffer(encode_mask_png(m), np.uint8), cv2.IMREAD_UNCHANGED) == m).all())
    True
    """
    if not isinstance(mask, np.ndarray) or mask.dtype != np.uint8 or mask.ndim != 2:
        raise InputError(f"encode_mask_png needs a (H, W) uint8 array, got {getattr(mask, 'dtype', type(mask))} "
                         f"{getattr(mask, 'shape', '')}")
    ok, buf = cv2.imencode(".png", mask, list(MASK_PNG_PARAMS))
    if not ok:  # pragma: no cover
        raise InputError(f"OpenCV could not encode a mask of shape {mask.shape} as PNG")
    return buf.tobytes()


def encode_jpeg(rgb: np.ndarray, *, quality: int = JPEG_QUALITY) -> bytes:
    """Encode an RGB frame as a baseline JPEG (what robots send).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        RGB order (converted to OpenCV's BGR here); grey and RGBA accepted.
    quality : int, keyword-only
        1..100 (default :data:`JPEG_QUALITY` = 90).

    Returns
    -------
    jpeg : bytes
    """
    q = int(quality)
    if not 1 <= q <= 100:
        raise InputError(f"JPEG quality must be 1..100, got {quality}")
    rgb = as_rgb(rgb, name="rgb")
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, q])
    if not ok:  # pragma: no cover
        raise InputError(f"OpenCV could not encode an array of shape {rgb.shape} as JPEG")
    return buf.tobytes()
