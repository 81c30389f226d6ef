"""The drivable-region pipeline (pure numpy / numba / OpenCV; no Zenoh, no rerun).

Public API (re-exported here, imported lazily so ``scmr --help`` stays fast)::

    decode_frame, load_frame, encode_jpeg,
    decode_image, load_image, resize_frame, area_resize,
    encode_png                                                codec
    segment_drivable, DrivableResult, warm_up                 pipeline
    gaussian_blur_3x3, srm, roi, bottom_centre,
    dominant_channel, histogram, otsu_threshold,
    sobel_magnitude, remove_sparse_pixels, fill_columns,
    red_green, overlay                                         the SPEC 1 steps

Frames are ``(H, W, 3) uint8`` RGB; masks are ``(225, 300) uint8`` with
255 = drivable.  See docs/PIPELINE.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from scmr_mesh._lazy import lazy_exports

_EXPORTS = {
    "decode_image": "codec",
    "decode_frame": "codec",
    "load_frame": "codec",
    "encode_jpeg": "codec",
    "MAX_PROGRESSIVE_PIXELS": "codec",
    "load_image": "codec",
    "resize_frame": "codec",
    "area_resize": "codec",
    "encode_png": "codec",
    "encode_mask_png": "codec",
    "MAX_PIXELS": "codec",
    "FRAME_SHAPE": "codec",
    "segment_drivable": "pipeline",
    "DrivableResult": "pipeline",
    "warm_up": "pipeline",
    "MODES": "pipeline",
    "srm": "srm",
    "SrmResult": "srm",
    "gaussian_blur_3x3": "steps",
    "roi": "steps",
    "bottom_centre": "steps",
    "dominant_channel": "steps",
    "histogram": "steps",
    "otsu_threshold": "steps",
    "sobel_magnitude": "steps",
    "remove_sparse_pixels": "steps",
    "fill_columns": "steps",
    "red_green": "steps",
    "overlay": "steps",
}

__all__ = sorted(_EXPORTS)

# The function ``srm`` lives in the module ``srm``: import that (light) module now and
# bind the name to the function, so no later submodule import can shadow it.
from scmr_mesh.imaging import srm as _srm_module  # noqa: E402

srm = _srm_module.srm


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


if TYPE_CHECKING:  # pragma: no cover
    from scmr_mesh.imaging.codec import (
        FRAME_SHAPE,
        MAX_PIXELS,
        MAX_PROGRESSIVE_PIXELS,
        area_resize,
        decode_frame,
        decode_image,
        encode_jpeg,
        encode_mask_png,
        encode_png,
        load_frame,
        load_image,
        resize_frame,
    )
    from scmr_mesh.imaging.pipeline import (
        MODES,
        DrivableResult,
        segment_drivable,
        warm_up,
    )
    from scmr_mesh.imaging.srm import SrmResult, srm
    from scmr_mesh.imaging.steps import (
        bottom_centre,
        dominant_channel,
        fill_columns,
        gaussian_blur_3x3,
        histogram,
        otsu_threshold,
        overlay,
        red_green,
        remove_sparse_pixels,
        roi,
        sobel_magnitude,
    )
