"""Decoding, encoding and resizing of frames (SPEC section 1, step 1).

Every frame in scmr-mesh is an ``(H, W, 3) uint8`` array in **RGB** order.
OpenCV works in BGR; the functions here are the only place that converts, so
callers never have to think about it.

Decoding is defensive: the header is parsed *before* decoding so that a tiny
file that claims to be a 100 000 x 100 000 image (a decompression bomb) is
refused cheaply, and every failure raises
:class:`~scmr_mesh.errors.ImageDecodeError` with a message that says what was
received.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import cv2
import numpy as np

from scmr_mesh.errors import ImageDecodeError, InputError

log = logging.getLogger(__name__)

#: Width and height of the frame every pipeline stage works on (SPEC 1, step 1).
FRAME_WIDTH = 300
FRAME_HEIGHT = 225
FRAME_SHAPE = (FRAME_HEIGHT, FRAME_WIDTH)

#: Largest image (in pixels) :func:`decode_image` accepts: 50 Mpx.
MAX_PIXELS = 50_000_000

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_MAGIC = b"\xff\xd8"
# JPEG start-of-frame markers that carry the image size (not DHT/JPG/DAC).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _check_size(width: int, height: int, what: str) -> None:
    if width <= 0 or height <= 0:
        raise ImageDecodeError(f"{what} header gives an empty size {width}x{height}; the file is corrupt")
    if width * height > MAX_PIXELS:
        raise ImageDecodeError(
            f"{what} header claims {width}x{height} = {width * height} pixels, more than the "
            f"{MAX_PIXELS} allowed; refusing to decode (downscale the image first)"
        )


def _png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ImageDecodeError(f"truncated PNG: {len(data)} bytes, no complete IHDR header")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _jpeg_size(data: bytes) -> tuple[int, int, int]:
    """Return (width, height, offset after the SOF segment) of a JPEG."""
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
            return width, height, i + seg_len
        i += seg_len
    raise ImageDecodeError(f"truncated or corrupt JPEG: no frame header in {len(data)} bytes")


def decode_image(data: bytes, *, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Decode PNG/JPEG bytes (or raw RGB bytes) to an RGB frame.

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
        16-bit images are scaled to 8 bits.

    Raises
    ------
    ImageDecodeError
        Empty, truncated, not PNG/JPEG, corrupt, or larger than
        :data:`MAX_PIXELS` (checked from the header before decoding).

    Examples
    --------
    >>> rgb = decode_image(bytes(2 * 3 * 3), shape=(2, 3))
    >>> rgb.shape, rgb.dtype.name
    ((2, 3, 3), 'uint8')
    """
    if isinstance(data, (bytearray, memoryview)):
        data = bytes(data)
    if not isinstance(data, bytes):
        raise ImageDecodeError(f"image data must be bytes, got {type(data).__name__}")
    if len(data) == 0:
        raise ImageDecodeError("empty image data (0 bytes)")
    if shape is not None:
        try:
            height, width = (int(v) for v in shape)
        except (TypeError, ValueError):
            raise ImageDecodeError(f"shape must be (height, width), got {shape!r}") from None
        _check_size(width, height, "raw RGB")
        expected = height * width * 3
        if len(data) != expected:
            raise ImageDecodeError(
                f"raw RGB data for shape {height}x{width} must be {expected} bytes, got {len(data)}"
            )
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3).copy()

    if data.startswith(_PNG_MAGIC):
        width, height = _png_size(data)
        _check_size(width, height, "PNG")
        if data.rfind(b"IEND") < 0:
            raise ImageDecodeError(f"truncated PNG: {len(data)} bytes and no IEND chunk")
        kind = "PNG"
    elif data.startswith(_JPEG_MAGIC):
        width, height, after_sof = _jpeg_size(data)
        _check_size(width, height, "JPEG")
        if data.rfind(b"\xff\xd9", after_sof) < 0:
            raise ImageDecodeError(f"truncated JPEG: {len(data)} bytes and no end-of-image marker")
        kind = "JPEG"
    else:
        head = data[:8].hex()
        raise ImageDecodeError(
            f"not a PNG or JPEG image (first bytes {head}); pass PNG/JPEG, or raw RGB with shape=(H, W)"
        )

    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # pragma: no cover - OpenCV usually returns None
        raise ImageDecodeError(f"corrupt {kind} ({len(data)} bytes): {exc}") from None
    if img is None or img.size == 0:
        raise ImageDecodeError(f"corrupt or truncated {kind} ({len(data)} bytes): OpenCV could not decode it")
    return _to_rgb(img)


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


def load_image(path: str | Path) -> np.ndarray:
    """Read a PNG/JPEG file as an RGB frame.

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
        return decode_image(data)
    except ImageDecodeError as exc:
        raise ImageDecodeError(f"{p}: {exc}") from None


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
    return cv2.resize(rgb, (FRAME_WIDTH, FRAME_HEIGHT), interpolation=cv2.INTER_AREA)


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
