"""The small pipeline steps of SPEC section 1 (steps 2 and 4-9), one function each.

Each function is pure (array in, array or number out), checks its input and
says what it got when the input is wrong.  :mod:`scmr_mesh.imaging.pipeline`
strings them together.

References
----------
N. Otsu, "A threshold selection method from gray-level histograms",
IEEE Trans. SMC 9(1), pp. 62-66, 1979.
"""

from __future__ import annotations

import cv2
import numpy as np

from scmr_mesh.errors import InputError
from scmr_mesh.imaging.codec import as_rgb

#: RGB colours of the red/green map.
GREEN = (0, 255, 0)
RED = (255, 0, 0)


# --------------------------------------------------------------------- step 2
def gaussian_blur_3x3(rgb: np.ndarray) -> np.ndarray:
    """Smooth with the thesis's 3x3 Gaussian ``[[1,2,1],[2,4,2],[1,2,1]] / 16`` (Eq 3.2).

    Parameters
    ----------
    rgb : (H, W, 3) uint8

    Returns
    -------
    blurred : (H, W, 3) uint8
        Rounded to nearest; borders use reflection (``BORDER_REFLECT_101``,
        ``dcb|abcd|cba`` without repeating the edge pixel).
    """
    rgb = as_rgb(rgb, name="rgb")
    return cv2.GaussianBlur(rgb, (3, 3), 0, borderType=cv2.BORDER_REFLECT_101)


# ------------------------------------------------------------------ steps 4-5
def roi(image: np.ndarray) -> np.ndarray:
    """The region of interest: the lower half of the frame (thesis's "south-bound region").

    Parameters
    ----------
    image : (H, W, ...) array

    Returns
    -------
    lower : (H - H // 2, W, ...) view
        Rows ``H // 2`` to the bottom.
    """
    if not isinstance(image, np.ndarray) or image.ndim < 2 or image.shape[0] == 0:
        raise InputError(f"roi needs an image array with at least one row, got {getattr(image, 'shape', image)!r}")
    return image[image.shape[0] // 2 :]


def bottom_centre(region: np.ndarray) -> np.ndarray:
    """The bottom-centre cell of a 3x3 split of ``region`` (thesis Figure 3.12).

    Parameters
    ----------
    region : (M, N, ...) array
        Usually :func:`roi` of the frame.

    Returns
    -------
    cell : view
        Rows ``2M//3 .. M``, columns ``N//3 .. 2N//3`` (never empty: at least
        one row and column).
    """
    if not isinstance(region, np.ndarray) or region.ndim < 2 or 0 in region.shape[:2]:
        raise InputError(f"bottom_centre needs a non-empty image array, got {getattr(region, 'shape', region)!r}")
    m, n = region.shape[:2]
    r0 = min(2 * m // 3, m - 1)
    c0 = min(n // 3, n - 1)
    c1 = max(2 * n // 3, c0 + 1)
    return region[r0:, c0:c1]


def dominant_channel(rgb: np.ndarray) -> int:
    """The dominant colour channel ``Cc = argmax(N_R, N_G, N_B)`` (Eq 3.3).

    ``N_c`` is the sum of channel ``c`` over the pixels; ties go to the first
    channel (R before G before B).

    Parameters
    ----------
    rgb : (M, N, 3) uint8

    Returns
    -------
    channel : int
        0 (R), 1 (G) or 2 (B).
    """
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"dominant_channel needs an (M, N, 3) array, got {getattr(rgb, 'shape', rgb)!r}")
    sums = rgb.reshape(-1, 3).sum(axis=0, dtype=np.int64)
    return int(np.argmax(sums))


def histogram(values: np.ndarray) -> np.ndarray:
    """256-bin histogram of uint8 values.

    Parameters
    ----------
    values : uint8 array of any shape

    Returns
    -------
    counts : (256,) int64
    """
    if not isinstance(values, np.ndarray) or values.dtype != np.uint8:
        raise InputError(f"histogram needs a uint8 array, got {getattr(values, 'dtype', type(values))}")
    return np.bincount(values.ravel(), minlength=256).astype(np.int64)


# --------------------------------------------------------------------- step 6
def otsu_threshold(hist: np.ndarray) -> int:
    """Otsu's threshold of a histogram (Eq 3.5-3.9).

    Classes are ``C1 = {0..T}`` and ``C2 = {T+1..N-1}`` (so ``value > T`` is
    the upper class, as in Eq 3.4 and OpenCV).  Minimising the within-class
    variance ``q1 s1^2 + q2 s2^2`` (Eq 3.5) is the same as maximising the
    between-class variance ``q1 q2 (mu1 - mu2)^2`` because their sum is the
    fixed total variance; the latter is computed here from exact integer
    cumulative sums, ``(S1 n2 - S2 n1)^2 / (n1 n2)``, so equal candidates
    compare exactly equal and the lowest ``T`` wins a tie.

    A histogram with a single occupied bin ``v`` has no split; ``v`` is
    returned (every value is ``<= T``).

    Parameters
    ----------
    hist : (N,) array of non-negative counts
        Usually 256 bins.

    Returns
    -------
    T : int

    Raises
    ------
    InputError
        Not 1-D, negative counts, or all zero.

    Examples
    --------
    >>> h = np.zeros(256, np.int64); h[50] = 10; h[200] = 10
    >>> otsu_threshold(h)
    50
    """
    h = np.asarray(hist)
    if h.ndim != 1 or h.size == 0:
        raise InputError(f"otsu_threshold needs a 1-D histogram, got shape {h.shape}")
    if h.dtype.kind == "f":
        if not np.all(np.isfinite(h)) or np.any(h != np.round(h)):
            raise InputError("otsu_threshold needs integer counts, got non-integer values")
    h = h.astype(np.int64)
    if np.any(h < 0):
        raise InputError("otsu_threshold needs non-negative counts, got a negative count")
    if int(h.sum()) == 0:
        raise InputError("otsu_threshold got an empty histogram (all counts zero)")
    return otsu_of_counts(h)


def otsu_of_counts(h: np.ndarray) -> int:
    """:func:`otsu_threshold` of a 1-D int64 histogram with a count > 0, unchecked (the pipeline's own
    histograms).

    Computed over the occupied bins only: the class sums, and so the between-class variance,
    change only at an occupied bin, so the lowest ``T`` of the best run of equal candidates is
    an occupied bin, and the same integer sums give the same floating-point values there as the
    scan of all bins.  A histogram of SRM regions has a few dozen occupied bins: 20 us instead
    of 77 us for the 256-bin scan on this box with numpy, and about 27 us against numpy's 41 us
    of that with the Python loop used up to :data:`_OTSU_LOOP_BINS` bins.  The loop's integers are
    exact at any count; the numpy scan is used only where its int64 products cannot wrap.
    """
    occupied = np.flatnonzero(h)
    if occupied.size == 1:
        return int(occupied[0])
    counts = h[occupied].tolist()
    total = sum(counts)
    if occupied.size <= _OTSU_LOOP_BINS or total > _OTSU_INT64_TOTAL:
        # a few dozen bins: a Python loop over exact integers beats numpy's per-call overhead
        # (the same float64 operations in the same order, the first maximum: the same threshold).
        # A total above _OTSU_INT64_TOTAL takes it too: numpy's int64 products would wrap there.
        bins = occupied.tolist()
        sum_all = sum(b * c for b, c in zip(bins, counts))
        n1 = s1 = 0
        best, best_t = -1.0, bins[0]
        for b, c in zip(bins[:-1], counts[:-1]):  # the last occupied bin has nothing above it
            n1 += c
            s1 += b * c
            n2 = total - n1
            d = float(s1 * n2 - (sum_all - s1) * n1)
            sigma = d * d / (float(n1) * float(n2))
            if sigma > best:
                best, best_t = sigma, b
        return best_t
    n = h[occupied]
    n1 = np.cumsum(n)[:-1]  # the last occupied bin has nothing above it: not a split
    s1 = np.cumsum(n * occupied)
    total, sum_all = int(n1[-1] + n[-1]), int(s1[-1])
    s1 = s1[:-1]
    n2 = total - n1
    d = (s1 * n2 - (sum_all - s1) * n1).astype(np.float64)
    sigma_b = d * d / (n1.astype(np.float64) * n2.astype(np.float64))
    return int(occupied[int(np.argmax(sigma_b))])


#: :func:`otsu_of_counts` loops in Python up to this many occupied bins (an SRM cell's few dozen).
_OTSU_LOOP_BINS = 64
#: ... and for any histogram whose total count is above this: ``s1 * n2`` (up to 255 x total^2)
#: must fit in int64 for the numpy scan (before 2026-11-28 a total over about 2e8 wrapped silently).
_OTSU_INT64_TOTAL = 10**8


# --------------------------------------------------------------------- step 7
def sobel_magnitude(grey: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude ``sqrt(Gx^2 + Gy^2)`` with zero padding (Eq 3.10-3.11).

    Parameters
    ----------
    grey : (H, W) numeric array

    Returns
    -------
    magnitude : (H, W) float32
        Pixels outside the image count as 0, so a bright image has strong
        edges along its border (as the thesis specifies).

    Examples
    --------
    >>> g = np.zeros((5, 6), np.float32); g[:, 3:] = 10
    >>> float(sobel_magnitude(g)[2, 2])
    40.0
    """
    g = np.asarray(grey)
    if g.ndim != 2 or 0 in g.shape:
        raise InputError(f"sobel_magnitude needs a non-empty (H, W) array, got shape {g.shape}")
    g = g.astype(np.float32, copy=False)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_CONSTANT)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_CONSTANT)
    return cv2.magnitude(gx, gy)


# --------------------------------------------------------------------- step 8
def remove_sparse_pixels(
    drivable: np.ndarray, edges: np.ndarray | None = None, *, edge_threshold: float = np.inf
) -> np.ndarray:
    """Column-wise, bottom-up sparse-pixel removal (thesis Table 3.5).

    Each column is walked from the bottom row up; pixels stay drivable until
    the first non-drivable pixel or the first pixel whose edge magnitude is
    ``>= edge_threshold``; that pixel and everything above it become
    non-drivable.

    Parameters
    ----------
    drivable : (H, W) array
        Non-zero = drivable.
    edges : (H, W) float array, optional
        Edge magnitude (e.g. :func:`sobel_magnitude`).  Left out: only the
        first non-drivable pixel stops a column.
    edge_threshold : float, keyword-only
        Edge strength that stops a column.

    Returns
    -------
    mask : (H, W) uint8
        255 = drivable, 0 = not.
    """
    from scmr_mesh.imaging._aot import remove_sparse_kernel

    d = np.asarray(drivable)
    if d.ndim != 2 or 0 in d.shape:
        raise InputError(f"remove_sparse_pixels needs a non-empty (H, W) mask, got shape {d.shape}")
    d = np.ascontiguousarray(d != 0, dtype=np.uint8)
    if edges is None:
        e = np.zeros(d.shape, np.float32)
    else:
        e = np.ascontiguousarray(edges, dtype=np.float32)
        if e.shape != d.shape:
            raise InputError(f"edges shape {e.shape} does not match the mask shape {d.shape}")
    return remove_sparse_kernel(d, e, np.float32(edge_threshold))


def fill_columns(candidate: np.ndarray, *, max_gap: int = 10) -> np.ndarray:
    """Column-wise, bottom-up fill used by the ``best`` mode (a gap-tolerant Table 3.5).

    Each column is walked from the bottom row up.  It is drivable from the
    bottom up to the highest candidate pixel reached before a run of more than
    ``max_gap`` non-candidate pixels; everything above is not.  Holes such as
    lane markings are filled; a column whose bottom ``max_gap + 1`` pixels hold
    no candidate is empty.

    Parameters
    ----------
    candidate : (H, W) array
        Non-zero = drivable candidate.
    max_gap : int, keyword-only
        Longest run of non-candidate pixels bridged (>= 0).

    Returns
    -------
    mask : (H, W) uint8
        255 = drivable, 0 = not.
    """
    from scmr_mesh.imaging._aot import column_fill_kernel

    c = np.asarray(candidate)
    if c.ndim != 2 or 0 in c.shape:
        raise InputError(f"fill_columns needs a non-empty (H, W) mask, got shape {c.shape}")
    if int(max_gap) < 0:
        raise InputError(f"max_gap must be >= 0, got {max_gap}")
    return column_fill_kernel(np.ascontiguousarray(c != 0, dtype=np.uint8), int(max_gap))


# --------------------------------------------------------------------- step 9
def _as_mask(mask: np.ndarray) -> np.ndarray:
    m = np.asarray(mask)
    if m.ndim != 2 or 0 in m.shape:
        raise InputError(f"a mask must be a non-empty (H, W) array, got shape {m.shape}")
    return m != 0


def red_green(mask: np.ndarray) -> np.ndarray:
    """The red/green map: green = drivable, red = not.

    Parameters
    ----------
    mask : (H, W) array
        Non-zero = drivable.

    Returns
    -------
    rgb : (H, W, 3) uint8
        RGB order: (0, 255, 0) drivable, (255, 0, 0) not drivable.
    """
    m = _as_mask(mask)
    out = np.empty(m.shape + (3,), np.uint8)
    out[...] = RED
    out[m] = GREEN
    return out


def overlay(rgb: np.ndarray, mask: np.ndarray, *, alpha: float = 0.4) -> np.ndarray:
    """Blend the red/green map over an image.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The image (any size; the mask is resized to it with nearest neighbour).
    mask : (h, w) array
        Non-zero = drivable.
    alpha : float, keyword-only
        Weight of the red/green map, 0..1.

    Returns
    -------
    blended : (H, W, 3) uint8
    """
    rgb = as_rgb(rgb, name="rgb")
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha must be between 0 and 1, got {alpha}")
    m = _as_mask(mask).astype(np.uint8)
    if m.shape != rgb.shape[:2]:
        m = cv2.resize(m, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_NEAREST)
    return cv2.addWeighted(rgb, 1.0 - float(alpha), red_green(m), float(alpha), 0.0)
