"""The drivable-region pipeline: :func:`segment_drivable` (SPEC section 1).

Two modes:

``"thesis"``
    The dissertation's rules as written: Gaussian 3x3 -> SRM -> ROI (lower
    half) -> bottom-centre cell -> dominant channel -> Otsu ``T`` -> Appendix E
    binarisation over the whole SRM image (``(R+G+B) // 3 >= T`` is green) ->
    Sobel edges of the SRM grey image -> column-wise bottom-up sparse-pixel
    removal (a column stops at its first red pixel or strong edge).

``"best"`` (default)
    A road model learned from each frame itself: Gaussian -> tone curve ->
    SRM at ``16 * q`` -> the regions covering the bottom-centre cell seed a
    mixture of Gaussians over illumination-invariant colour, brightness and
    texture -> regions inside a seed's chi-square ellipsoid, below a horizon
    prior, 4-connected to the cell -> a gap-tolerant bottom-up column fill.
    See :mod:`scmr_mesh.imaging.road_model`, docs/PIPELINE.md, and
    docs/ACCURACY.md for the cross-validated choice of its few constants.
"""

from __future__ import annotations

import dataclasses
import numbers
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np

from scmr_mesh.errors import InputError
from scmr_mesh.imaging.codec import FRAME_SHAPE, area_resize, as_rgb, resize_frame
from scmr_mesh.imaging.road_model import (
    WORK_SHAPE,
    RoadParams,
    abstain,
    classify,
    cut_at_boundaries,
    cut_rough,
    straight_edges,
    tone_curve,
)
from scmr_mesh.imaging.srm import srm
from scmr_mesh.imaging.steps import (
    bottom_centre,
    dominant_channel,
    fill_columns,
    gaussian_blur_3x3,
    histogram,
    otsu_of_counts,
    otsu_threshold,
    remove_sparse_pixels,
    roi,
    sobel_magnitude,
)

MODES = ("best", "thesis")

#: Sobel magnitude that stops a column in sparse-pixel removal: the response
#: of a clean step of 32 grey levels (4 * 32).
THESIS_EDGE_THRESHOLD = 128.0


@dataclass
class DrivableResult:
    """Output of :func:`segment_drivable`.

    Attributes
    ----------
    mask : (225, 300) uint8
        255 = drivable, 0 = not.
    threshold : int
        Otsu threshold ``T`` of the bottom-centre histogram.
    timings_ms : dict of str to float
        Milliseconds per stage, including ``"resize"`` and ``"total"``
        (``total`` excludes ``resize``: it is the 300x225 frame to the mask).
    stages : dict of str to ndarray, or None
        With ``stages=True``: ``"frame"`` and ``"blur"`` (225, 300, 3), ``"srm"`` (225, 300, 3)
        region-mean image, ``"otsu"`` (225, 300) uint8 black/white image,
        ``"histogram"`` (256,) int64 counts, ``"edges"`` (225, 300) float32
        Sobel magnitude; plus ``"channel"`` (0-d int) the dominant channel.
    confidence : float or None
        ``best``: how far the road model trusts its seed, in [0, 1] (1 = the mask is the
        full road model; below 1 the mask was shrunk to the ground just ahead, see
        :func:`scmr_mesh.imaging.road_model.abstain`).  ``thesis``: None (no model).
    abstained : str or None
        Why the mask was shrunk to what the model is sure of (one of
        :data:`scmr_mesh.imaging.road_model.ABSTAIN_REASONS`), or None.
    carried : str or None
        With a ``track``: what the carried road model did (one of
        :data:`scmr_mesh.imaging.road_track.CARRIED`); None without one.
    """

    mask: np.ndarray
    threshold: int
    timings_ms: dict = field(default_factory=dict)
    stages: dict | None = None
    confidence: float | None = None
    abstained: str | None = None
    carried: str | None = None


def _clock() -> float:
    return time.perf_counter() * 1000.0


#: The constants of ``best`` (chosen by leave-one-dataset-out cross-validation).
DEFAULT_PARAMS = RoadParams()


def srm_q(mode: str, q: float = 32, params: RoadParams | None = None) -> float:
    """The SRM Q a mode runs with for the user's ``q``.

    ``thesis`` uses ``q`` as given.  ``best`` runs SRM on the half-size working frame
    with ``params.q`` (2048) scaled by ``q / 32``, so the default ``q = 32`` gives ``params.q``.
    """
    if mode == "best":
        try:
            q = float(q)
        except (TypeError, ValueError):
            raise InputError(f"q must be a positive number, got {q!r}") from None
        return (params or DEFAULT_PARAMS).q * q / 32.0
    return q


def segment_drivable(
    rgb: np.ndarray, *, mode: str = "best", q: float = 32, stages: bool = False,
    params: RoadParams | None = None, track=None, track_params=None, t: float | None = None,
) -> DrivableResult:
    """Find the drivable region of a camera frame.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        RGB frame of any size (grey (H, W) and RGBA are accepted too); it is
        resized to 300x225 first.
    mode : {"best", "thesis"}, keyword-only
        ``"best"`` (most accurate) or ``"thesis"`` (the dissertation's rules).
    q : float, keyword-only
        SRM complexity parameter Q.  ``thesis`` uses it as given; ``best``
        runs SRM on the half-size working frame with ``params.q * q / 32`` (2048 by default).
    stages : bool, keyword-only
        Also return the intermediate images.
    params : RoadParams, optional, keyword-only
        Constants of ``best`` (default :data:`DEFAULT_PARAMS`); ignored by ``thesis``.
    track : RoadTrack, optional, keyword-only
        ``best`` only: a road model carried across one robot's frames
        (:mod:`scmr_mesh.imaging.road_track`), updated in place; pass the frames in order.
        A new (cold) track gives exactly the mask without one.
    track_params : TrackParams, optional, keyword-only
        The carried model's constants (default ``TrackParams()``).
    t : float, optional, keyword-only
        The frame's time in seconds (for the track's ``max_gap_s``).

    Returns
    -------
    DrivableResult

    Raises
    ------
    InputError
        Unknown mode, bad q, or an array that is not an RGB image.

    Examples
    --------
    >>> from scmr_mesh.imaging.synthetic import make_scene
    >>> img, truth = make_scene("structured_road", seed=1)
    >>> segment_drivable(img).mask.shape
    (225, 300)
    """
    if mode not in MODES:
        raise InputError(f"mode must be one of {', '.join(MODES)}; got {mode!r}")
    timings = {}
    t0 = _clock()
    rgb = as_rgb(rgb, name="rgb")
    frame = resize_frame(rgb)
    t1 = _clock()
    timings["resize"] = t1 - t0

    params = (params or DEFAULT_PARAMS).check() if mode == "best" else None
    if track is not None and params is None:
        raise InputError("a carried road model (track) needs mode 'best'; thesis has no road model to carry")
    if params is not None:
        carry = None
        if track is not None:
            from scmr_mesh.imaging.road_track import TrackParams

            if t is not None and (isinstance(t, bool) or not isinstance(t, numbers.Real) or not np.isfinite(t)):
                raise InputError(f"t must be a finite time in seconds, got {t!r}")
            carry = (track, (track_params or TrackParams()).check(), t)
        return _segment_best(frame, q, stages, params, timings, t1, carry)
    blurred = gaussian_blur_3x3(frame)
    t2 = _clock()
    timings["blur"] = t2 - t1

    seg = srm(blurred, q=srm_q(mode, q))
    palette = np.rint(seg.means).clip(0, 255).astype(np.uint8)
    srm_img = palette[seg.labels]
    t3 = _clock()
    timings["srm"] = t3 - t2

    window = palette[bottom_centre(roi(seg.labels))]
    channel = dominant_channel(window)
    hist = histogram(np.ascontiguousarray(window[:, :, channel]))
    threshold = otsu_threshold(hist)
    t4 = _clock()
    timings["otsu"] = t4 - t3

    grey = srm_img.sum(axis=2, dtype=np.int32) // 3
    edges = sobel_magnitude(grey)
    t5 = _clock()
    timings["edges"] = t5 - t4

    otsu_bw = np.where(grey >= threshold, 255, 0).astype(np.uint8)
    t6 = _clock()
    timings["classify"] = t6 - t5
    mask = remove_sparse_pixels(otsu_bw, _inner_edges(edges), edge_threshold=THESIS_EDGE_THRESHOLD)
    t7 = _clock()
    timings["sparse"] = t7 - t6
    timings["total"] = t7 - t1

    out_stages = None
    if stages:
        out_stages = {
            "frame": frame,
            "blur": blurred,
            "srm": srm_img,
            "otsu": otsu_bw,
            "histogram": hist,
            "edges": edges,
            "channel": np.array(channel),
        }
    return DrivableResult(mask=mask, threshold=int(threshold), timings_ms=timings, stages=out_stages)


def _segment_best(frame: np.ndarray, q: float, stages: bool, params: RoadParams, t: dict, t1: float,
                  carry=None) -> DrivableResult:
    """``best`` on a 300x225 frame: half-size working frame, SRM, the road model, column fill, upsampled mask.

    Stage names as in ``thesis``: ``blur`` is the area downsampling (a box low-pass that
    replaces the 3x3 Gaussian), ``otsu`` the bottom-centre threshold (returned, not used),
    ``edges`` empty, ``sparse`` the column fill and the upsampling to 300x225.
    """
    wh, ww = WORK_SHAPE
    small = area_resize(frame, ww, wh)
    t2 = _clock()
    t["blur"] = t2 - t1

    seg = srm(tone_curve(small, params.gamma) if params.gamma != 1.0 else small, q=srm_q("best", q, params))
    palette = np.rint(seg.means).clip(0, 255).astype(np.uint8)
    t3 = _clock()
    t["srm"] = t3 - t2

    # the thesis's bottom-centre cell of the 300x225 frame, read off the working labels
    channel, hist, threshold = cell_otsu(seg.labels, palette)
    t4 = _clock()
    t["otsu"] = t4 - t3
    t["edges"] = 0.0

    mask, confidence, abstained, t6, carried = _best_mask(small, seg, params, carry, frame=frame)
    t["classify"] = t6 - t4
    t7 = _clock()
    t["sparse"] = t7 - t6
    t["total"] = t7 - t1

    out_stages = None
    if stages:
        def full(img: np.ndarray) -> np.ndarray:
            return cv2.resize(img, (FRAME_SHAPE[1], FRAME_SHAPE[0]), interpolation=cv2.INTER_NEAREST)

        srm_img = full(palette[seg.labels])
        grey = srm_img.sum(axis=2, dtype=np.int32) // 3
        out_stages = {
            "frame": frame,
            "blur": full(small),
            "srm": srm_img,
            "otsu": _otsu_class_image(srm_img[:, :, channel], palette[seg.labels[_cell_index()]][:, :, channel],
                                      threshold),
            "histogram": hist,
            "edges": sobel_magnitude(grey),
            "channel": np.array(channel),
        }
    return DrivableResult(mask=mask, threshold=int(threshold), timings_ms=t, stages=out_stages,
                          confidence=confidence, abstained=abstained, carried=carried)


#: :class:`RoadParams` fields read only after :func:`classify` (by :func:`_best_mask` and :func:`abstain`):
#: :func:`best_masks` classifies once for all params that differ only in these.  A new field is
#: left out of this list, so it keys the classification (slower, never wrong).
AFTER_CLASSIFY = ("opening", "reach", "cap", "standing", "gap", "boundary", "rough")


def _best_mask(small: np.ndarray, seg, params: RoadParams, carry=None,
               classified: tuple[np.ndarray, dict] | None = None, edges: dict | None = None,
               frame: np.ndarray | None = None):
    """The road model on SRM regions of the working frame.

    Returns mask (225, 300), confidence, abstained, the clock after classify, and ``carried``
    (None without ``carry = (track, track_params, t)``).  ``classified``: :func:`classify`'s
    result for these params, shared between calls (copied here, never changed), else computed.
    ``edges``: a cache of this frame's :func:`~scmr_mesh.imaging.road_model.straight_edges` by
    ``boundary`` and candidate, shared between calls (filled here).  ``frame``: the 300x225 frame
    ``small`` was made from, needed when ``params.rough`` is on (its fine texture).
    """
    def opening(candidate: np.ndarray) -> np.ndarray:
        if params.opening > 1:
            return cv2.morphologyEx(candidate, cv2.MORPH_OPEN, np.ones((1, int(params.opening)), np.uint8))
        return candidate

    carried = None
    if carry is None:
        if classified is not None:  # abstain marks info (open_ground) and may edit the candidate
            candidate, info = classified[0].copy(), dict(classified[1])
        else:
            candidate, info = classify(small, seg, params)
        candidate, confidence, abstained = abstain(opening(candidate), info, params)
        lowest = info.get("open_ground", False)
    else:
        from scmr_mesh.imaging.road_track import tracked_candidate

        track, tparams, t = carry
        flags: dict = {}
        candidate, confidence, abstained, carried = tracked_candidate(small, seg, params, track, tparams, t, opening,
                                                                      flags)
        lowest = flags["open_ground"]
    if params.boundary > 0:
        lines = None
        if edges is not None:   # the same candidate under other constants: the same edges
            key = (params.boundary, candidate.tobytes())
            lines = edges.get(key)
            if lines is None:
                lines = edges[key] = straight_edges(small, candidate, params.boundary)
        candidate = cut_at_boundaries(candidate, small, params.boundary, lines)[0]
    if params.rough > 0:
        if frame is None:
            raise ValueError("the rough-surface cut (params.rough > 0) needs the 300x225 frame")
        candidate = cut_rough(candidate, small, frame, params.rough)
    t6 = _clock()
    gap = int(round(params.gap * WORK_SHAPE[1] / FRAME_SHAPE[1]))
    small_mask = column_fill(candidate, gap, lowest)
    up = cv2.resize(small_mask, (FRAME_SHAPE[1], FRAME_SHAPE[0]), interpolation=cv2.INTER_LINEAR)
    # cv2.threshold: the bytes of np.where(up >= 128, 255, 0), 0.005 ms instead of 0.23
    return cv2.threshold(up, 127, 255, cv2.THRESH_BINARY)[1], confidence, abstained, t6, carried


def column_fill(candidate: np.ndarray, gap: int, lowest: bool) -> np.ndarray:
    """``best``'s column fill of the candidate (working frame): :func:`~scmr_mesh.imaging.steps.fill_columns`.

    With ``lowest`` (the frame is open ground, :func:`~scmr_mesh.imaging.road_model.open_ground`),
    a column whose bottom ``gap + 1`` rows hold no candidate (a rock or the lens's dark corner at
    the bottom of the frame) is not dropped: it is filled from its lowest candidate pixel up, by
    the same rule, and stays empty below that pixel.  The candidate is 4-connected to the seed
    and the ground runs on to the horizon across the frame, so such a column is ground beyond
    an obstacle, not an island.  (As a cross-validated constant for every frame it was neutral
    on the 60 labelled images: mean IoU 0.7968 either way, precision 0.8905 -> 0.8886.)  For the
    same reason the candidate above a gap longer than ``gap`` (the sand beyond a rock) stays
    where it is one 4-connected piece with what the fill reached: the column fill stops there,
    but the robot reaches that ground around the rock (synthetic desert 0.767 -> 0.781; no mask
    of the 60 labelled images changes, 2026-11-29).  A piece the fill did not reach stays out (the
    carried model's candidate and the boundary cut can hold pieces apart from the seed).
    """
    if not lowest:
        return fill_columns(candidate, max_gap=gap)
    c = candidate != 0
    h = c.shape[0]
    has = c.any(axis=0)
    low = h - 1 - np.argmax(c[::-1], axis=0)
    below = (np.arange(h)[:, None] > low[None, :]) & (has & (h - 1 - low > gap))[None, :]
    filled = fill_columns(c | below, max_gap=gap)
    filled[below] = 0
    n, comp = cv2.connectedComponents(c.astype(np.uint8), connectivity=4)
    reached = np.zeros(n, bool)
    reached[comp[(filled > 0) & c]] = True
    reached[0] = False   # the background
    filled[reached[comp]] = 255
    return filled


def best_masks(rgb: np.ndarray, params_list, *, q: float = 32):
    """``best``'s masks of one frame for several :class:`RoadParams`, running SRM once per distinct (q, gamma).

    Yields ``(mask, confidence, abstained)`` in the order of ``params_list``; each mask equals
    ``segment_drivable(rgb, params=params).mask`` (used by cross-validation).  :func:`classify`
    runs once per distinct SRM and params other than :data:`AFTER_CLASSIFY`.
    """
    frame = resize_frame(as_rgb(rgb, name="rgb"))
    wh, ww = WORK_SHAPE
    small = area_resize(frame, ww, wh)
    segs: dict = {}
    classified: dict = {}
    edges: dict = {}
    for params in params_list:
        params = params.check()
        key = (srm_q("best", q, params), params.gamma)
        if key not in segs:
            segs[key] = srm(tone_curve(small, params.gamma) if params.gamma != 1.0 else small, q=key[0])
        ckey = (key, dataclasses.replace(params, **{f: RoadParams.__dataclass_fields__[f].default
                                                    for f in AFTER_CLASSIFY}))
        if ckey not in classified:
            classified[ckey] = classify(small, segs[key], params)
        mask, confidence, abstained, _t, _c = _best_mask(small, segs[key], params, classified=classified[ckey],
                                                         edges=edges, frame=frame)
        yield mask, confidence, abstained


class WorkingFrame(NamedTuple):
    """What ``best`` computes of a frame before its road model: :func:`working_frame`'s result."""

    #: the half-size working frame, (112, 150, 3) uint8 RGB
    small: np.ndarray
    #: its SRM regions
    seg: object
    #: the 300x225 frame it was made from, (225, 300, 3) uint8 RGB (the rough-surface cut's texture)
    frame: np.ndarray


def working_frame(rgb: np.ndarray, params: RoadParams | None = None, *, q: float = 32) -> WorkingFrame:
    """``best``'s working frame of ``rgb``, its SRM regions and the 300x225 frame, for :func:`best_mask_from`."""
    params = (params or DEFAULT_PARAMS).check()
    frame = resize_frame(as_rgb(rgb, name="rgb"))
    wh, ww = WORK_SHAPE
    small = area_resize(frame, ww, wh)
    seg = srm(tone_curve(small, params.gamma) if params.gamma != 1.0 else small, q=srm_q("best", q, params))
    return WorkingFrame(small, seg, frame)


def best_mask_from(work: WorkingFrame, params: RoadParams | None = None, *, track=None, track_params=None,
                   t: float | None = None):
    """``best``'s ``(mask, confidence, abstained, carried)`` from :func:`working_frame`'s output.

    Equals what :func:`segment_drivable` returns for the same frame, params and track (used by
    the sequence cross-validation, which runs SRM once per frame and the road model many times).
    """
    params = (params or DEFAULT_PARAMS).check()
    carry = None
    if track is not None:
        from scmr_mesh.imaging.road_track import TrackParams

        carry = (track, (track_params or TrackParams()).check(), t)
    mask, confidence, abstained, _t, carried = _best_mask(work.small, work.seg, params, carry, frame=work.frame)
    return mask, confidence, abstained, carried


_CELL_INDEX: list = []


def _cell_index() -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices into the working frame of every pixel of the 300x225 bottom-centre cell."""
    if not _CELL_INDEX:
        h, w = FRAME_SHAPE
        cr = bottom_centre(roi(np.broadcast_to(np.arange(h)[:, None], (h, w))))[:, 0]
        cc = bottom_centre(roi(np.broadcast_to(np.arange(w)[None, :], (h, w))))[0]
        wh, ww = WORK_SHAPE
        _CELL_INDEX[:] = np.ix_(cr * wh // FRAME_SHAPE[0], cc * ww // FRAME_SHAPE[1])  # one store: thread-safe
    return _CELL_INDEX[0], _CELL_INDEX[1]


_CELL_BLOCK: list = []


def _cell_block() -> tuple[slice, slice, np.ndarray]:
    """The working frame's block under the 300x225 bottom-centre cell, and how many cell pixels each of its pixels is."""
    if not _CELL_BLOCK:
        ry, rx = (a.ravel() for a in _cell_index())
        y0, x0 = int(ry.min()), int(rx.min())
        my, mx = np.bincount(ry - y0), np.bincount(rx - x0)
        _CELL_BLOCK[:] = (slice(y0, y0 + my.size), slice(x0, x0 + mx.size),
                          (my[:, None] * mx[None, :]).ravel().astype(np.float64))  # one store: thread-safe
    return _CELL_BLOCK[0], _CELL_BLOCK[1], _CELL_BLOCK[2]


def cell_otsu(labels: np.ndarray, palette: np.ndarray) -> tuple[int, np.ndarray, int]:
    """The dominant channel, histogram and Otsu threshold of the 300x225 bottom-centre cell of an SRM result.

    Every pixel of a region has its region's colour (``palette[label]``), so the cell is known
    from how many of its pixels each region holds: its channel sums are ``counts @ palette``
    and its histogram is ``counts`` binned by the regions' values.  Those are the same integers
    as :func:`dominant_channel` and :func:`histogram` of the cell's pixels (``palette[labels]``
    over the cell, then a channel of it), without making the 75x100x3 window: about 0.25 ms
    less per frame, the stage's numpy overhead.

    Parameters
    ----------
    labels : (112, 150) int
        Region label of each working-frame pixel (``srm(...).labels``).
    palette : (n, 3) uint8
        Each region's colour.

    Returns
    -------
    channel : int
        0 (R), 1 (G) or 2 (B), ties to the first.
    hist : (256,) int64
    threshold : int
    """
    rows, cols, weights = _cell_block()
    # the cell's pixels map to a block of working pixels, each repeated a fixed number of times:
    # the counts are the block's, weighted (exact integers in float64); 0.01 ms instead of 0.03
    counts = np.bincount(labels[rows, cols].ravel(), weights=weights, minlength=len(palette)).astype(np.int64)
    channel = int(np.argmax(counts @ palette.astype(np.int64)))
    hist = np.bincount(palette[:, channel], weights=counts, minlength=256).astype(np.int64)
    return channel, hist, otsu_of_counts(hist)


def _inner_edges(edges: np.ndarray) -> np.ndarray:
    """Edge magnitude with the one-pixel frame border zeroed.

    Zero padding makes the frame border itself a strong edge; left in, the
    bottom row would stop every column at once.
    """
    inner = edges.copy()
    inner[0, :] = 0
    inner[-1, :] = 0
    inner[:, 0] = 0
    inner[:, -1] = 0
    return inner


def _otsu_class_image(channel_img: np.ndarray, window_channel: np.ndarray, threshold: int) -> np.ndarray:
    """255 where a pixel is in the Otsu class that holds most bottom-centre pixels."""
    upper_in_window = int(np.count_nonzero(window_channel > threshold))
    if upper_in_window * 2 > window_channel.size:
        return np.where(channel_img > threshold, 255, 0).astype(np.uint8)
    return np.where(channel_img <= threshold, 255, 0).astype(np.uint8)


def warm_up() -> None:
    """Compile (or load from the cache) every numba kernel by running both modes once.

    The frame starts at 320x240 (a 640x480 JPEG as a service decodes it), so its resize to
    300x225 runs :func:`~scmr_mesh.imaging.codec.area_resize`'s kernels too.
    """
    img = np.zeros((240, 320, 3), np.uint8)
    img[img.shape[0] // 2 :] = 90
    img[: img.shape[0] // 2] = 200
    for mode in MODES:
        segment_drivable(img, mode=mode)
    # the boundary cut's kernels, called directly (whether a frame reaches them depends on it):
    # a grey ground whose right part, beyond a diagonal, is brighter and redder
    from scmr_mesh.imaging._aot import boundary_cut_kernel, boundary_sides_kernel
    from scmr_mesh.imaging.road_model import BOUNDARY_SIDES, FEATURE_OFFSET

    wh, ww = WORK_SHAPE
    small = np.full((wh, ww, 3), 90, np.uint8)
    yy, xx = np.mgrid[0:wh, 0:ww]
    small[xx > ww // 2 + 20 + (wh - 1 - yy)] = (200, 150, 120)
    candidate = np.zeros((wh, ww), np.uint8)
    candidate[wh // 3:] = 1
    line = np.array([[95, 111, 149, 57]], np.int64)
    boundary_sides_kernel(line, candidate, small, np.array(BOUNDARY_SIDES, np.float64), float(FEATURE_OFFSET))
    boundary_cut_kernel(candidate, line, 0.5)
    cut_at_boundaries(candidate, small, DEFAULT_PARAMS.boundary or 0.3)
    cut_rough(candidate, small, cv2.resize(small, (FRAME_SHAPE[1], FRAME_SHAPE[0])), 1.75)
