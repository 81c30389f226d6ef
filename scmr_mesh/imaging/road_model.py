"""The ``best`` mode: a road model learned from each frame itself (self-supervised).

No constant in here was fitted to the evaluation images' labels by hand: the
few that remain (:class:`RoadParams`) are chosen by leave-one-dataset-out
cross-validation (:func:`scmr_mesh.imaging.evaluate.cross_validate`, ``scmr
eval --cv``), and docs/ACCURACY.md reports the cross-validated scores beside
the in-sample ones.

Steps, on the frame area-downsampled to 150x112 (:data:`WORK_SHAPE`):

1. **Regions.**  SRM with Q = 2048 (``RoadParams.q``; the CV grid's choice on the 60 shared images).
2. **Self-supervised seeds** (:func:`seed_regions`).  The regions that cover at least
   ``seed_share`` of the thesis's bottom-centre cell and reach its lower half (ground
   contact: a vehicle ahead ends above it) are taken to be road, as Stanley's vision
   system took the patch the laser scanners had found drivable (Dahlkamp et al. 2006).
3. **A per-frame appearance model.**  Each seed region gives one Gaussian (mean and
   covariance of its pixels) over four pixel features: ``log(R/G)``, ``log(B/G)``
   (Alvarez et al.'s illuminant-invariant idea), log-brightness and log texture
   (Sobel magnitude).  A sunlit seed's Gaussian is widened along
   :data:`SHADE_DIRECTION` on its shaded side only, so the same surface in shade still
   matches while a brighter, warmer verge does not pass the pixel test as the road "in more
   sun" (the weak-border join's chromaticity test keeps the symmetric term).
4. **Classification.**  A region is road-like when at least ``frac`` of its pixels lie
   inside the ``p``-quantile chi-square(4) ellipsoid of some seed.
5. **Geometry.**  Only road-like regions 4-connected to a seed stay, grown over weak borders
   (:func:`candidate_regions`: a region of a seed's chromaticity, or, beside a seed below
   ``sunlit``, of the chromaticity that seed's surface has under more sun or shade); the
   caller's column fill bridges lane markings.

References
----------
H. Dahlkamp, A. Kaehler, D. Stavens, S. Thrun, G. Bradski, "Self-supervised
monocular road detection in desert terrain", Robotics: Science and Systems, 2006.
J. M. Alvarez, A. M. Lopez, "Road detection based on illuminant invariance",
IEEE Trans. ITS 12(1), pp. 184-193, 2011.
R. Nock, F. Nielsen, "Statistical region merging", IEEE TPAMI 26(11), 2004.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import NamedTuple

import cv2
import numpy as np

from scmr_mesh.errors import InputError
from scmr_mesh.imaging.steps import bottom_centre, roi


#: ``best`` works on the frame area-downsampled to this size (rows, columns): half of 300x225.
#: SRM's cost is linear in the pixel count, and the labels of a half-size frame hold the
#: road as well as the full frame's (oracle IoU 0.92 at Q = 4096 against 0.90 at full size
#: and Q = 1024, docs/ACCURACY.md).
WORK_SHAPE = (112, 150)


@dataclass(frozen=True)
class RoadParams:
    """The constants of the self-supervised road model (defaults: chosen by cross-validation).

    Attributes
    ----------
    gamma : float
        Tone curve exponent of SRM's input (1 = linear).
    q : float
        SRM's Q on the half-size working frame.
    seed_share : float
        A region seeds the road model when it covers this share of the bottom-centre cell.
    p : float
        Quantile of the chi-square(4) ellipsoid around a seed Gaussian: a pixel inside
        the ellipsoid of some seed looks like road.
    frac : float
        A region is road-like when at least this share of its pixels looks like road.
    noise : float
        Isotropic standard deviation added to every seed covariance (feature units).
    shade : float
        Standard deviation (feature units) added to a sunlit seed's Gaussian along
        :data:`SHADE_DIRECTION`, so the road in shade and in sun is one surface (0 = off).
        It counts on the shaded side only (``v^T C0^-1 (x - mu) >= 0``, ``C0`` the covariance
        without it: the pixel's most likely amount of shade): shade only darkens, so a brighter,
        warmer pixel is tested without it (continuous: both distances agree on that boundary).
    sunlit : float
        A seed whose mean log brightness is at least ``log(sunlit + 10)`` (about: whose mean
        grey level is at least this) is taken to be in sunlight and gets the shade term; a
        darker seed (overcast, dusk, a tunnel, a dark surface in the sun) does not, and gets the
        weak-border join's shade line instead (:func:`candidate_regions`).
    horizon : float
        Rows above this fraction of the height are never drivable (0 = no prior).
    gap : int
        Longest run of non-road pixels (in 300x225 frame pixels) the column fill bridges.
    opening : int
        Width (working-frame pixels) of a horizontal opening of the candidate mask before the
        column fill: it removes road-like strips narrower than this, such as tree trunks, poles
        and building edges joined to the road (0 or 1 = off).
    reach : float
        The seed is weak when its candidate mask reaches above this fraction of the height
        (it has leaked into what stands on the ground: trunks, buildings, the sky; 0 = never).
    dim : float
        The seed is weak when its mean grey level is below this (dusk, night; 0 = never).
    cap : float
        When the seed is weak the mask shrinks to the rows below this fraction of the height,
        the part of the frame the robot is sure is ground (see :func:`abstain`).
    standing : bool
        When the seed is weak, also drop the non-seed regions with most of their pixels above
        ``cap`` (they stand on the ground: walls, trunks, building bases).
    front : float
        A candidate that reaches above ``reach`` is *open ground*, not a leak, when its upper
        edge is a horizon: a flat front over at least this share of the frame's width, with sky
        room above it (see :func:`open_ground`; 0 = never, the abstention as before).
    lateral : float
        A seed region other than the one covering most of the bottom-centre cell is dropped when
        its centroid lies outside ``[lateral, 1 - lateral]`` of the frame's width and it reaches
        above the cell: it is a verge, pavement or field running beside the road, not the
        surface ahead (see :func:`seed_regions`; 0 = off).
    weak : float
        The weak-border join (see :func:`candidate_regions`): a region that does not look like
        a seed joins the candidate across a border running across the frame whose mean Sobel
        magnitude is at most ``weak`` x the seed pixels' median, when its chromaticity is a
        seed's, or, beside a seed below ``sunlit``, the seed's under more sun or shade (a
        shadow's edge, a change of texture or a faint seam in one surface; 0 = off).
    boundary : float
        Cut the candidate along the road's boundaries (see :func:`cut_at_boundaries`): a straight
        edge spanning at least this share of the height along x or y (at least
        :data:`BOUNDARY_MIN_LENGTH`), running up the frame through the candidate
        between two surfaces of different material (a kerb, a verge's edge line, a wall's foot);
        only the robot's side stays (0 = off).
    rough : float
        Cut the candidate's rough surfaces (see :func:`cut_rough`): where the fine texture of the
        300x225 frame is more than this multiple of the candidate's median texture in the same
        row (one distance from the camera), over a surface of at least :data:`ROUGH_MIN_AREA`
        working pixels, the candidate is not asphalt but cobbles, paving slabs or a littered
        verge that SRM joined to it by colour (0 = off, the default; else > 1).  At 1.75 it lifts
        KITTI semantics' precision 0.800 -> 0.839 on the shared frames, but a blur over part of
        a row (a water drop, mud, motion blur on part of the lens) makes the sharp road beside it
        rough.  The blur guard (:data:`ROUGH_BLUR_SPREAD`, :data:`ROUGH_SHARPER`) keeps the blurs
        of the second review (the left 60 % blurred: mean IoU 0.783 off and on, 0.634 unguarded),
        but not a strong blur over the bottom centre (a drop of radius 70 px, sigma 3: 0.808 ->
        0.754, a third review), so it is off by default and out of the cross-validation grid
        (docs/ACCURACY.md).
    """

    gamma: float = 1.0
    q: float = 2048.0
    seed_share: float = 0.10
    p: float = 0.9
    frac: float = 0.3
    noise: float = 0.02
    shade: float = 0.2
    sunlit: float = 80.0
    horizon: float = 0.0
    gap: int = 20
    opening: int = 9
    reach: float = 0.35
    dim: float = 0.0
    cap: float = 0.5
    standing: bool = True
    front: float = 0.97
    lateral: float = 0.25
    weak: float = 6.0
    boundary: float = 0.3
    rough: float = 0.0

    def check(self) -> RoadParams:
        if not 0 < self.gamma <= 4:
            raise InputError(f"gamma must be in (0, 4], got {self.gamma}")
        if not (self.q > 0 and math.isfinite(self.q)):
            raise InputError(f"q must be a positive finite number, got {self.q}")
        if not 0 < self.seed_share <= 1:
            raise InputError(f"seed_share must be in (0, 1], got {self.seed_share}")
        if not 0 < self.p < 1:
            raise InputError(f"p must be in (0, 1), got {self.p}")
        if not 0 < self.frac <= 1:
            raise InputError(f"frac must be in (0, 1], got {self.frac}")
        if not self.noise > 0:
            raise InputError(f"noise must be > 0, got {self.noise}")
        if not (0 <= self.shade and math.isfinite(self.shade)):
            raise InputError(f"shade must be a finite number >= 0, got {self.shade}")
        if not (0 <= self.sunlit <= 255):
            raise InputError(f"sunlit must be a grey level in [0, 255], got {self.sunlit}")
        if not 0 <= self.horizon < 1:
            raise InputError(f"horizon must be in [0, 1), got {self.horizon}")
        if int(self.gap) < 0:
            raise InputError(f"gap must be >= 0, got {self.gap}")
        if not 0 <= int(self.opening) <= 64:
            raise InputError(f"opening must be an integer width in [0, 64], got {self.opening}")
        if not 0 <= self.reach < 1:
            raise InputError(f"reach must be in [0, 1), got {self.reach}")
        if not 0 <= self.dim <= 255:
            raise InputError(f"dim must be a grey level in [0, 255], got {self.dim}")
        if not 0 <= self.cap < 1:
            raise InputError(f"cap must be in [0, 1), got {self.cap}")
        if not 0 <= self.front <= 1:
            raise InputError(f"front must be a share of the width in [0, 1], got {self.front}")
        if not 0 <= self.lateral < 0.5:
            raise InputError(f"lateral must be a share of the width in [0, 0.5), got {self.lateral}")
        if not (0 <= self.weak and math.isfinite(self.weak)):
            raise InputError(f"weak must be a finite multiple of the seed's median edge strength >= 0 "
                             f"(0 = off), got {self.weak}")
        if not (self.boundary == 0 or BOUNDARY_MIN_LENGTH <= self.boundary < 1):
            raise InputError(f"boundary must be 0 (off) or a share of the height in [{BOUNDARY_MIN_LENGTH}, 1) "
                             f"(shorter edges are texture, not kerbs), got {self.boundary}")
        if not (self.rough == 0 or (1 < self.rough and math.isfinite(self.rough))):
            raise InputError(f"rough must be 0 (off) or a finite multiple of the row's median texture > 1 "
                             f"(at 1 or below half the road is rough), got {self.rough}")
        return self

    def as_dict(self) -> dict:
        return asdict(self)


#: Feature offset (grey levels) inside the logarithms: the sensor noise floor,
#: so a near-black pixel's chromaticity does not explode.
FEATURE_OFFSET = 10.0
N_FEATURES = 4

#: How far a full shadow moves a grey surface's features (the length of the move that
#: :data:`SHADE_DIRECTION` is the unit vector of, about 1.28): the weak-border join's shade line
#: (:func:`candidate_regions`) reaches no further either way.
FULL_SHADE = math.sqrt(0.18**2 + 0.41**2 + 1.2**2)
#: How shade moves a surface's features (log R/G, log B/G, log brightness, texture), as a unit
#: vector: in the shadow of a clear sky's sun a grey surface keeps about 0.25 / 0.3 / 0.45 of
#: its red / green / blue light (skylight only), so log R/G falls by 0.18, log B/G rises by 0.41
#: and log brightness falls by about 1.2 (Finlayson et al.'s illuminant direction; Alvarez and
#: Lopez use the same idea for shadow-invariant road detection).  Texture does not change.
SHADE_DIRECTION = np.array([-0.18, 0.41, -1.2, 0.0]) / FULL_SHADE


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p``-quantile of the chi-square distribution with integer ``dof`` (bisection on the CDF).

    Examples
    --------
    >>> round(chi2_quantile(0.95, 4), 4)
    9.4877
    """
    def cdf(x: float) -> float:
        # regularized lower incomplete gamma P(dof/2, x/2), by its series
        a, z = dof / 2.0, x / 2.0
        if z <= 0:
            return 0.0
        term = total = 1.0 / a
        n = 1
        while term > total * 1e-15 and n < 10_000:
            term *= z / (a + n)
            total += term
            n += 1
        return min(1.0, math.exp(-z + a * math.log(z) - math.lgamma(a)) * total)

    lo, hi = 0.0, 10.0 * dof + 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


_LUTS: dict = {}


def tone_curve(image: np.ndarray, gamma: float) -> np.ndarray:
    """``255 * (v / 255) ** gamma``, rounded, through a cached 256-entry table."""
    lut = _LUTS.get(gamma)
    if lut is None:
        lut = np.clip(np.rint(255.0 * (np.arange(256) / 255.0) ** gamma), 0, 255).astype(np.uint8)
        _LUTS[gamma] = lut
    return cv2.LUT(image, lut)


def feature_tables(off: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lookup tables of the pixel features (plain numpy, built once per offset by the caller).

    ``lut[v] = log(v + off)`` (v = 0..255), ``lsum[v] = log(v / 3 + off)`` (v = R+G+B = 0..765),
    ``tex[v] = log1p(v / 8)`` (v = rounded Sobel magnitude, 0..2047).
    """
    lut = np.log(np.arange(256, dtype=np.float64) + off)
    lsum = np.log(np.arange(766, dtype=np.float64) / 3.0 + off)
    tex = np.log1p(np.arange(2048, dtype=np.float64) / 8.0)
    return lut, lsum, tex


_CHI2: dict = {}
#: The pixel-feature lookup tables, built at import (3,070 floats, microseconds): a lazy cache
#: filled by whichever thread came first let threads warming the pipeline at once (the 16
#: robots of a ``scmr swarm``) each append the tables, and the kernel got 16 arguments instead of 13.
_TABLES: tuple[np.ndarray, np.ndarray, np.ndarray] = feature_tables(FEATURE_OFFSET)


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel-feature lookup tables (:data:`_TABLES`)."""
    return _TABLES


def seed_regions(labels: np.ndarray, n_regions: int, share: float, lateral: float = 0.0) -> np.ndarray:
    """The self-supervised seeds: regions covering ``share`` of the bottom-centre cell and touching its lower half.

    The second condition is a ground-contact check: the road is the surface the robot
    stands on, so in a forward camera it continues down to the cell's lower rows, while
    a vehicle ahead stands *on* the road and ends above them (its lower edge is road).
    When no region passes both tests, the ground under the robot is fragmented into regions
    smaller than ``share`` of the cell (leaf litter, gravel, a patchwork of shade): the seeds are
    then all the regions that reach the cell's lower half, the ground the robot stands on, and
    :func:`classify` reports the seed as not ground, so :func:`abstain` shrinks the mask to the
    rows below ``cap`` (issue 27: before, the largest region of the cell alone was the seed, and
    a forest floor of leaf litter kept a fraction of its own ground).

    With ``lateral`` > 0, a seed other than the one covering most of the cell is dropped when its
    centroid lies outside ``[lateral, 1 - lateral]`` of the width *and* it reaches above the cell
    (its top row is above the cell's): the surface ahead of a forward camera is centred in the
    frame, while a verge, pavement or field that runs beside the road reaches into the cell's
    corner with most of its pixels to one side, up along the road.  Such a region's Gaussian
    would make everything of its appearance road-like (issue 27: lateral over-fill).  A piece
    of the road's own surface in the cell's corner (a patch of shade or of new asphalt near the
    robot) lies within the cell's rows and stays a seed.

    Examples
    --------
    >>> lab = np.zeros((112, 150), np.int32); lab[56:, 125:] = 1; lab[100:, 80:] = 1   # a verge beside the road
    >>> seed_regions(lab, 2, 0.1).tolist(), seed_regions(lab, 2, 0.1, 0.25).tolist()
    ([0, 1], [0])
    >>> litter = (np.arange(112)[:, None] // 4 * 38 + np.arange(150)[None, :] // 4).astype(np.int32)
    >>> seed_regions(litter, int(litter.max()) + 1, 0.1).size   # 4x4 patches: 39 in the cell's lower half
    39
    """
    return _seeds_grounded(labels, n_regions, share, lateral)[0]


def _seeds_grounded(labels: np.ndarray, n_regions: int, share: float, lateral: float = 0.0) -> tuple[np.ndarray, bool]:
    """:func:`seed_regions`, and whether some region passed both its share and ground-contact tests."""
    cell = bottom_centre(roi(labels))
    counts = np.bincount(cell.ravel(), minlength=n_regions)
    low = np.bincount(cell[cell.shape[0] // 2:].ravel(), minlength=n_regions)
    seeds = np.flatnonzero((counts >= share * cell.size) & (low > 0))
    grounded = seeds.size > 0
    if not grounded:
        # the ground under the robot is fragmented (leaf litter, gravel): it is all of it
        seeds = np.flatnonzero(low > 0)
    if lateral > 0 and seeds.size > 1:
        h, w = labels.shape
        top = h - cell.shape[0]   # the cell ends at the frame's bottom
        lo, hi = lateral * (w - 1), (1 - lateral) * (w - 1)
        main = seeds[np.argmax(counts[seeds])]
        flat = labels.ravel()
        keep = []
        for s in seeds.tolist():
            if s != main:
                at = np.flatnonzero(flat == s)   # row-major: at[0] is in the region's top row
                # the mean column, an integer sum over the count as before (same float)
                centre = float(int((at % w).sum())) / max(at.size, 1)
                if not lo <= centre <= hi and at.size and at[0] < top * w:
                    continue   # off to one side and running up beside the road
            keep.append(s)
        seeds = np.array(keep, dtype=seeds.dtype)
    return seeds, grounded


def classify(small: np.ndarray, seg, params: RoadParams) -> tuple[np.ndarray, dict]:
    """Candidate road pixels of a working frame from its SRM regions (before the column fill).

    Parameters
    ----------
    small : (h, w, 3) uint8
        The working frame (features are measured on it, not on the tone-mapped one).
    seg : SrmResult
        SRM of the tone-mapped working frame.
    params : RoadParams

    Returns
    -------
    candidate : (h, w) uint8
        1 = road-like and 4-connected to a seed region, or joined to those over weak borders
        (:func:`candidate_regions`).
    info : dict
        ``seeds`` (region labels), ``road_regions`` (count), ``road_share`` (per region,
        the share of its pixels inside a seed ellipsoid), ``seed_grey`` (mean grey level of
        the seed pixels; NaN unless ``params.dim`` > 0), ``grounded`` (False when no region
        had both the share and ground contact, so the cell's fragments were taken instead), and for
        :func:`abstain` ``labels``, ``sizes`` (pixels per region) and ``grad`` (Sobel magnitude
        of the grey working frame, for :func:`open_ground`'s sky test), ``weak_joined``
        ((k,) bool, the regions the weak-border join added; all False when ``params.weak`` is 0),
        and for :func:`open_ground`'s front and :func:`horizon_line` ``chroma`` ((k, 3), each
        region's mean log R/G, log B/G, log brightness), ``mus`` / ``covs`` (the seeds'
        Gaussians) and ``small`` (the working frame itself, not a copy).
    """
    from scmr_mesh.imaging._aot import road_share_kernel

    labels = seg.labels
    h, w = labels.shape
    k = seg.n_regions
    seeds, grounded = _seeds_grounded(labels, k, params.seed_share, params.lateral)
    slot = np.full(k, -1, np.int32)
    slot[seeds] = np.arange(seeds.size, dtype=np.int32)
    grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    grad = grey_gradient(grey)
    limit = _CHI2.get(params.p)
    if limit is None:
        limit = _CHI2[params.p] = chi2_quantile(params.p, N_FEATURES)
    inside, mus, covs, chroma, gmed = road_share_kernel(labels, small, grad, slot, int(k), *_tables(),
                                                        float(params.noise) ** 2, float(limit),
                                                        SHADE_DIRECTION, float(params.shade) ** 2,
                                                        math.log(params.sunlit + FEATURE_OFFSET))
    share = inside / np.maximum(seg.sizes, 1)
    road = share >= params.frac
    road[seeds] = True
    cand, joined = candidate_regions(road, slot >= 0, labels, grad, (chroma, gmed), mus, covs, params)
    seed_grey = float("nan")
    if params.dim > 0:
        seed_px = np.take(slot, labels) >= 0
        seed_grey = float(grey.astype(np.float32)[seed_px].mean()) if seed_px.any() else 0.0
    return cand, {"seeds": seeds, "road_regions": int(road.sum()), "road_share": share,
                  "seed_grey": seed_grey, "grounded": grounded, "labels": labels,
                  "sizes": seg.sizes, "grad": grad, "weak_joined": joined,
                  "chroma": chroma, "mus": mus, "covs": covs, "small": small}


#: :func:`candidate_regions`'s weak-border join has a fixed geometry (chosen on the synthetic scenes and by eye in the
#: prototype of 2026-11-28, not by the cross-validation; docs/ACCURACY.md): a joining region's
#: mean chromaticity within this Mahalanobis distance of a seed's (the seed Gaussian's chromatic
#: block, brightness free: a soft shadow's edge or a haze gradient changes brightness more than
#: hue; beside a seed below ``sunlit`` the shade line also allows the hue shift of shade) ...
WEAK_CHROMA = 2.0
#: ... its top row below this share of the height (the join never reaches the sky) ...
WEAK_TOP = 0.4
#: ... across a border with at least this share of its neighbour pairs vertical (it runs across
#: the frame, like the far edge of a shadow or a seam in the surface ahead; a border running up
#: the frame is a kerb or a verge's edge) ...
WEAK_ACROSS = 0.6


def candidate_regions(road: np.ndarray, is_seed: np.ndarray, labels: np.ndarray, grad: np.ndarray,
                      stats: tuple, mus: np.ndarray, covs: np.ndarray,
                      params: RoadParams) -> tuple[np.ndarray, np.ndarray]:
    """The candidate road of :func:`classify`, with the weak-border join: ``(candidate, joined)``.

    Without the join (``params.weak`` 0) the candidate is :func:`connected_to_seeds`'s: the
    road-like regions 4-connected to a seed region.  It is found by a search over the region
    graph (``candidate_kernel``, the same masks; the graph is needed for the join anyway).

    The weak-border join (issue 27's recall cue): a region that is not road-like joins when it is
    4-adjacent to the candidate across a border whose strength (the mean over its neighbouring
    pixel pairs of their mean Sobel magnitude) is at most ``params.weak`` x the median magnitude
    of the seed pixels, with at least :data:`WEAK_ACROSS` of those pairs vertical neighbours, and
    when its mean chromaticity lies within :data:`WEAK_CHROMA` of a seed's (the chromatic block of
    the seed's Gaussian) and its top row below :data:`WEAK_TOP` of the height.  A seed below
    ``sunlit`` (mean log brightness under ``log(sunlit + offset)``; its Gaussian has no shade
    term) is in shade or is a dark surface in the sun, and the same surface under more sun is
    less blue, under more shade bluer, not only brighter or darker: so a region may also pass on
    its chromaticity less the shift :data:`SHADE_DIRECTION` gives for its change in brightness
    (``t v``, ``t = lift / v[2]``, ``lift`` its mean log brightness less the seed's, ``|t|`` at
    most :data:`FULL_SHADE`: one full shadow), against the same block.  This is colour's own
    ambiguity, not a proof: a grey surface in shade and a sand-coloured one in the sun lie on
    one such line (a grey-60 seed and a (220, 190, 130) region, a review's case), so only the
    border's gates (weak, across the frame, below :data:`WEAK_TOP`) keep such a region out.
    (Issue 27: the synthetic structured road's seed 0 sits in a cast shadow and lost
    the sunlit road beyond it, 0.57 -> 0.90; the dirt road's seed 4, grey 78 in the sun, lost
    the road beyond a shadow band, 0.43 -> 0.98.  Widening such a seed's chromatic block by the
    shade term instead, which frees the chromaticity along v whatever the brightness, let CamVid
    0016E5_02160's pale pavement join: 0.888 -> 0.782.)  The road-like
    regions that a joined region connects to the candidate join too, and so on to the fixed
    point.  The road's far part in the shade of a tree, or past a change of surface texture, has
    the seed's hue but not its brightness or texture, so the per-pixel test misses it; the border
    it shares with the road is weak, while a verge's, a wall's or a car's is an edge.  (The
    numpy prototype of 2026-11-28 iterated :func:`connected_to_seeds` up to 10 times; the search
    gave the same masks on the 60 images and the 40 synthetic scenes at ``weak`` 4 and 6, with the
    symmetric shade term of then, measured on 2026-11-28 against the prototype, which is not in
    the repository.)

    ``road`` and ``is_seed`` are per region; ``stats`` is ``road_share_kernel``'s
    ``(chroma, gmed)`` (``chroma`` (k, 3): each region's mean log R/G, log B/G and log
    brightness) (when the seed pixels' median magnitude is 0, a flat synthetic seed, the
    limit is ``weak`` Sobel units); ``joined`` (k,) bool names the regions the weak borders added (not the
    road-like ones they connected).  With ``params.horizon`` > 0 (a cut through regions) the
    candidate is :func:`connected_to_seeds`'s, grown by rounds of the join until one adds nothing.
    """
    from scmr_mesh.imaging._aot import candidate_kernel

    chroma, gmed = stats
    h = labels.shape[0]
    k = road.size
    if chroma.shape != (k, 3):   # the kernel reads three columns unchecked
        raise ValueError(f"region means must be ({k}, 3), got {chroma.shape}")

    def search(start, passable):
        return candidate_kernel(labels, grad, start, passable, int(k), chroma, float(gmed), mus, covs,
                                float(params.weak), WEAK_CHROMA, WEAK_TOP * h, WEAK_ACROSS,
                                SHADE_DIRECTION, math.log(params.sunlit + FEATURE_OFFSET), FULL_SHADE)

    if params.horizon <= 0:
        inc, joined = search(is_seed, road)
        return np.take(inc.view(np.uint8), labels), joined
    # a horizon cuts regions, so connectivity is the pixels' (connected_to_seeds), and the join
    # runs in rounds: each round's search passes only through the candidate
    cand = connected_to_seeds(road, labels, is_seed, params)
    grown = road.copy()
    while params.weak > 0:
        in_c = np.bincount(labels[cand > 0], minlength=k) > 0
        new = search(in_c, in_c)[1] & ~grown
        if not new.any():
            break
        grown |= new
        cand = connected_to_seeds(grown, labels, is_seed, params)
    # a region joined above the horizon only is cut with the rows: it is not in the candidate
    in_c = np.bincount(labels[cand > 0], minlength=k) > 0
    return cand, grown & ~road & in_c


def connected_to_seeds(road: np.ndarray, labels: np.ndarray, is_seed: np.ndarray, params: RoadParams,
                       *, anywhere: bool = False) -> np.ndarray:
    """The road-like regions 4-connected to a seed region: (h, w) uint8, 1 = candidate road.

    ``road`` and ``is_seed`` are per-region booleans (``is_seed`` implies ``road``).  A seed is
    found through its pixels in the bottom-centre cell (:func:`seed_regions` takes seeds from
    there), or, with ``anywhere``, through any of its pixels (the carried model's seeds,
    :mod:`scmr_mesh.imaging.road_track`, may lie beside the cell).
    """
    h = labels.shape[0]
    # np.take: fancy indexing's result, 3x faster on these label maps
    cand = np.take(road.astype(np.uint8), labels)
    if params.horizon > 0:
        cand[: int(params.horizon * h)] = 0
    n_comp, comp = cv2.connectedComponents(cand, connectivity=4)
    keep = np.zeros(n_comp, np.uint8)
    if anywhere:
        keep[comp[np.take(is_seed, labels) & (cand > 0)]] = 1
    else:
        # SRM regions are 4-connected, so a seed lies in one component: any of its cell pixels names it
        cell_lab = bottom_centre(roi(labels))
        cell_comp = bottom_centre(roi(comp))
        keep[cell_comp[is_seed[cell_lab]]] = 1
    keep[0] = 0
    return np.take(keep, comp)


def grey_gradient(grey: np.ndarray) -> np.ndarray:
    """The 3x3 Sobel magnitude of a uint8 grey image, (h, w) float32 (reflected border), correctly rounded.

    ``cv2.spatialGradient`` gives both derivatives in one pass, in int16: the same values as
    two float ``cv2.Sobel`` calls on the image as float32 (exact small integers).  The sum of
    their squares is exact in float32 (at most 2 x 1020^2 < 2^24), so ``sqrt`` of it is the
    correctly rounded magnitude.  ``cv2.magnitude``, used before, is not: on the same values it
    gave a result one unit in the last place away from it for about a third of random inputs,
    and which result depended on where the arrays lay in memory (a copy of the same array could
    give the other), so a frame's ``grad`` could differ by a bit between runs.
    """
    dx, dy = cv2.spatialGradient(grey)
    sq = dx.astype(np.int32)
    sq *= sq
    dy32 = dy.astype(np.int32)
    dy32 *= dy32
    sq += dy32
    return np.sqrt(sq.astype(np.float32))


def pixel_features(small: np.ndarray, grad: np.ndarray | None = None) -> np.ndarray:
    """The road model's four features of every pixel, (h * w, 4) float64, as the kernel computes them.

    ``log(fR/fG)``, ``log(fB/fG)``, ``log((fR+fG+fB)/3)`` (f = channel + :data:`FEATURE_OFFSET`) and
    ``log1p(round(grad)/8)`` with ``grad`` the Sobel magnitude of the grey image (computed when
    not given), clipped to 0..2047.  Plain numpy (the carried model's path; the per-frame model
    computes the same values inside ``road_share_kernel``).
    """
    lut, lsum, tex = _tables()
    if grad is None:
        grad = grey_gradient(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY))
    r, g, b = (small[..., c].astype(np.intp) for c in range(3))
    gi = np.floor(np.clip(grad.astype(np.float64), 0.0, 2047.0) + 0.5).astype(np.intp)
    gi[~(grad < 2047.0)] = 2047
    feats = np.stack([lut[r] - lut[g], lut[b] - lut[g], lsum[r + g + b], tex[gi]], axis=-1)
    return feats.reshape(-1, N_FEATURES)


#: :func:`open_ground`'s fixed geometry, as fractions of the working frame: the highest row of the
#: candidate is the one reached by this share of the columns (a spike of a few columns, a pole or
#: a rock's top, does not set it) ...
FRONT_SPIKE = 0.05
#: ... the front is the columns whose top lies within this share of the height below that row
#: (the far edge of open ground is flat, the horizon) ...
FRONT_BAND = 0.1
#: ... and above that row at least this share of the height holds no candidate (room for the sky:
#: a candidate that climbed walls, an arch or a trunk reaches the top edge).
SKY_ROOM = 0.1


def open_ground(candidate: np.ndarray, front: float, grad: np.ndarray | None = None,
                info: dict | None = None) -> bool:
    """Whether a candidate that reaches high does so because the ground is open (desert, a field).

    Ground seen from a robot ends at the horizon, a straight line across the whole frame with the
    sky above it; what stands on the ground (a wall, a trunk, a building base) ends at its own
    top, which is not flat across the frame, and a forest's canopy is no sky.  So the candidate's
    upper edge is a horizon when

    * its highest row (the one :data:`FRONT_SPIKE` of the columns reach) leaves :data:`SKY_ROOM`
      of the height above it empty of candidate (room for the sky);
    * at least ``front`` of the columns have their highest candidate pixel within
      :data:`FRONT_BAND` of the height below the candidate's highest row.  With ``info`` (from
      :func:`classify`, holding the working frame) the candidate's :func:`horizon_line` is
      found (and left in ``info["horizon"]``: on open ground :func:`abstain` cuts the candidate
      there, which only ever removes candidate).  The front is measured on the candidate as it
      is, never on the cut one: cutting first let a wall of the ground's colour, standing on the
      ground with its top above the horizon, pass with a flat front (2026-11-29, two reviews;
      ACCURACY.md).  When a line was found, a column whose candidate stops
      lower still counts if, below the line and between the front's band and its top, it holds
      a region of the seed's surface (:func:`same_surface`: its hue, or its hue in more shade)
      whose top lies in the band or within :data:`FRONT_BAND` above it: the same ground
      running on to the horizon, only darker than the seed's model lets in (the lens's dark
      corner, a shadow near the horizon, the sand beyond a rock at the frame's edge);
    * and (with ``grad``, the Sobel magnitude of the grey frame) the top :data:`SKY_ROOM` of the
      frame is smoother than the candidate (mean ``log1p(grad / 8)``, the road model's texture
      feature): a clear or overcast sky is the smoothest thing in an outdoor frame, while
      foliage, buildings and rock faces are at least as textured as the ground seen near.

    On the 60 labelled images no frame whose seed reaches above ``reach`` passes these tests
    (docs/ACCURACY.md), so cross-validation cannot choose ``front``; the synthetic desert is
    the case it is for.

    Examples
    --------
    >>> flat = np.zeros((112, 150), np.uint8); flat[40:] = 1
    >>> open_ground(flat, 0.7)
    True
    >>> trunk = np.zeros((112, 150), np.uint8); trunk[60:] = 1; trunk[5:60, 70:80] = 1
    >>> open_ground(trunk, 0.7)
    False
    """
    if front <= 0 or not candidate.any():
        return False
    if grad is not None:   # the sky test first: it is cheap, and the front may look for a horizon line
        room = int(SKY_ROOM * candidate.shape[0])
        texture = np.log1p(np.rint(np.clip(grad, 0, 2047)) / 8.0)
        if not float(texture[:room].mean()) < float(texture[candidate > 0].mean()):
            return False
    return front_share(candidate, info) >= front


def front_share(candidate: np.ndarray, info: dict | None = None) -> float:
    """:func:`open_ground`'s front: the share of the columns on it (0 for an empty candidate or one
    with no room for a sky above its highest row).  With ``info`` holding the working frame its
    :func:`horizon_line` is found and left in ``info["horizon"]`` (for :func:`abstain`'s cut), and
    with the seeds' Gaussians too a column below the band counts when the seed's surface runs on
    there, below that line, up to the band (see :func:`open_ground`)."""
    h, w = candidate.shape
    has = candidate.any(axis=0)
    if not has.any():
        return 0.0
    tops = np.where(has, candidate.argmax(axis=0), h)
    hi = _front_top(tops)
    if hi < int(SKY_ROOM * h):
        return 0.0
    band = hi + FRONT_BAND * h
    ok = has & (tops <= band)
    line = None
    if info is not None and "small" in info:
        horizon = info["horizon"] = horizon_line(info["small"], candidate)
        if horizon is not None:
            line = horizon.rows(w)
    if line is not None and "mus" in info and not ok.all():
        labels = info["labels"]
        k = info["sizes"].size
        rtop = np.full(k, h, np.int64)   # each region's top row
        for y in range(h - 1, -1, -1):
            rtop[labels[y]] = y
        runs_on = same_surface(info) & (rtop <= band) & (rtop >= hi - FRONT_BAND * h)
        rows = np.arange(h)[:, None]
        at = (rows > band) & (rows < tops[None, :]) & (rows >= line[None, :])   # below the horizon
        ok |= has & (np.take(runs_on, labels) & at).any(axis=0)
    return float(np.mean(ok))


def same_surface(info: dict) -> np.ndarray:
    """Per region, (k,) bool: its mean chromaticity is a seed's surface, in the same light or in more shade.

    The weak-border join's hue test (:data:`WEAK_CHROMA` on the chromatic block of a seed's
    Gaussian) without its border gates, with the shade line for every seed but only towards
    shade (a region darker than the seed by ``lift`` in log brightness is tested at its
    chromaticity less ``t`` x :data:`SHADE_DIRECTION`'s, ``t = lift / v[2]`` clipped to
    0..:data:`FULL_SHADE`).  A seed whose hue test also passes neutral grey (log R/G = log B/G
    = 0: asphalt, concrete) names no region: in a street the walls, the pavement and the poles
    are of that hue too (CamVid 0016E5_02040's facades and poles passed, 2026-11-29).  A
    tinted asphalt (the synthetic structured road's) is not grey by this test, so there the
    verges of its hue may count (:func:`front_share` asks for a horizon line above them too).
    ``info``: :func:`classify`'s (``chroma``, ``mus``, ``covs``).
    """
    chroma, mus, covs = info["chroma"], info["mus"], info["covs"]
    v = SHADE_DIRECTION
    out = np.zeros(chroma.shape[0], bool)
    for j in range(mus.shape[0]):
        c = covs[j, :2, :2]
        det = c[0, 0] * c[1, 1] - c[0, 1] * c[0, 1]
        if not det > 0:
            continue
        inv = np.array([[c[1, 1], -c[0, 1]], [-c[0, 1], c[0, 0]]]) / det
        if mus[j, :2] @ inv @ mus[j, :2] <= WEAK_CHROMA ** 2:
            continue   # a grey seed: its hue is also the walls', the concrete's and the poles'
        t = np.clip((chroma[:, 2] - mus[j, 2]) / v[2], 0.0, FULL_SHADE)
        for shift in (0.0, t[:, None] * v[None, :2]):
            d = chroma[:, :2] - mus[j, :2] - shift
            out |= np.einsum("ni,ij,nj->n", d, inv, d) <= WEAK_CHROMA ** 2
    return out


#: :func:`horizon_line`'s fixed geometry (chosen on the synthetic desert's seeds 0-7 on 2026-11-29,
#: not by the cross-validation: no labelled frame is open ground; docs/ACCURACY.md): the rows
#: searched run from 2 above the candidate's top row down this share of the height ...
HORIZON_DEPTH = 0.2
#: ... a step is the chromaticity (R, G, B over their sum, L1) of this many rows above a row
#: against as many from it down, after a box of :data:`HORIZON_BLUR` columns ...
HORIZON_ROWS = 3
HORIZON_BLUR = 9
#: ... the line's slope at most this (about 10 degrees of roll) ...
HORIZON_SLOPE = 0.18
#: ... and it holds the strongest step (a peak of the column's step profile, at least
#: :data:`BOUNDARY_CHROMA`) of this share of the columns within a row; the lowest such line is the
#: horizon.  (The true horizons of desert seeds 0-7 hold 0.61-1.00 of the columns, the hills' tops
#: above them 0.28-0.67, seed 6's cast shadow's edge 0.49.)  The sides are not tested as materials:
#: in seeds 2 and 3 the hills differ from the far sand by little more than a shade move (0.013 and
#: 0.031 once the move along :data:`SHADE_DIRECTION` is taken out, against 0.08-0.16 in the
#: others), so geometry decides; a level shadow's edge taken for the horizon costs the ground
#: beyond it (recall), never green on what is not ground.
HORIZON_SUPPORT = 0.6


class Horizon(NamedTuple):
    """A line of :func:`horizon_line`: in column ``x`` of a frame ``w`` wide it lies on row
    ``row + slope * (x - w / 2)``."""
    slope: float
    row: float

    def rows(self, w: int) -> np.ndarray:
        """The line's row in each of ``w`` columns (int64)."""
        return np.rint(self.row + self.slope * (np.arange(w) - w / 2)).astype(np.int64)


def horizon_line(small: np.ndarray, candidate: np.ndarray) -> Horizon | None:
    """The horizon of open ground: the lowest long, near-level boundary between two materials near
    the candidate's top, as a :class:`Horizon` (its slope and its row at the frame's centre
    column), or None.

    On open ground the ground's far edge is a near-level line across the frame; above it stand
    distant hills, dunes or a treeline that SRM may merge with the ground (their colour close
    to the far ground's), so the candidate runs on above the horizon.  Each column's strongest
    chromaticity step in the rows searched (at a peak of its profile) votes for its row; a line
    (slope within :data:`HORIZON_SLOPE`, a Hough vote over the slopes, then least squares on the
    votes within a row of it) that gathers :data:`HORIZON_SUPPORT` of the columns is a boundary.
    Boundaries are looked for again below each one found, and the lowest is taken: the sky's
    edge over the hills lies above the hills' foot.
    """
    h, w = candidate.shape
    has = candidate.any(axis=0)
    if not has.any():
        return None
    top = _front_top(np.where(has, candidate.argmax(axis=0), h))
    r0 = max(top - 2, HORIZON_ROWS)
    r1 = min(h - HORIZON_ROWS, top + int(HORIZON_DEPTH * h))
    if r1 <= r0:
        return None
    lo = r0 - HORIZON_ROWS   # the steps read the rows lo .. r1 + HORIZON_ROWS
    f = small[lo:r1 + HORIZON_ROWS].astype(np.float32) + np.float32(FEATURE_OFFSET)
    chroma = cv2.blur(f / f.sum(axis=2, keepdims=True), (HORIZON_BLUR, 1))
    cs = np.concatenate([np.zeros((1, w, 3), np.float32), np.cumsum(chroma, axis=0)])
    ys = np.arange(r0, r1)
    at = ys - lo
    step = np.abs((cs[at] - cs[at - HORIZON_ROWS]) - (cs[at + HORIZON_ROWS] - cs[at])).sum(axis=2) / HORIZON_ROWS
    x = np.arange(w) - w / 2
    slopes = np.linspace(-HORIZON_SLOPE, HORIZON_SLOPE, 37)
    found = None
    below = np.full(w, r0)
    # a column votes only at a peak of its step profile (a boundary's flanks are no boundaries)
    peak = np.ones_like(step, bool)
    peak[1:] &= step[1:] >= step[:-1]
    peak[:-1] &= step[:-1] >= step[1:]
    step = np.where(peak, step, 0)
    for _ in range(r1 - r0):   # each line found raises ``below`` by 2 rows or more on half the columns
        allowed = np.where(ys[:, None] >= below[None, :], step, 0)
        row, strength = ys[np.argmax(allowed, axis=0)], allowed.max(axis=0)
        vote = strength >= BOUNDARY_CHROMA
        if not vote.any():
            break
        # a Hough vote: per slope, the votes' intercepts binned by row, summed over 3 rows
        b = np.rint(row[vote][None, :] - slopes[:, None] * x[vote][None, :]).astype(np.int64)
        b0 = int(b.min())
        nb = int(b.max()) - b0 + 3
        counts = np.bincount((np.arange(slopes.size)[:, None] * nb + b - b0 + 1).ravel(),
                             minlength=slopes.size * nb).reshape(slopes.size, nb)
        window = counts[:, :-2] + counts[:, 1:-1] + counts[:, 2:]   # centred on bins 1 .. nb - 2
        si, bi = np.unravel_index(int(window.argmax()), window.shape)
        best = (int(window[si, bi]), float(slopes[si]), int(bi + b0))
        if best[0] < HORIZON_SUPPORT * w:
            break
        # the line through the votes of the best bin and its neighbours (least squares)
        inl = vote & (np.abs(row - (best[2] + best[1] * x)) <= 1.5)
        if np.count_nonzero(inl) < 2:
            break
        slope, b = np.polyfit(x[inl], row[inl].astype(np.float64), 1)
        line = np.rint(b + slope * x).astype(np.int64)
        found = (float(slope), float(b))
        below = np.maximum(below, line + HORIZON_ROWS)
    return None if found is None else Horizon(found[0], found[1])


def cut_above_horizon(candidate: np.ndarray, info: dict, horizon: Horizon) -> np.ndarray:
    """The candidate less what lies above the ``horizon`` line, then only what still touches a seed
    region (``info``'s ``labels``, ``sizes`` and ``seeds``)."""
    h, w = candidate.shape
    line = horizon.rows(w)
    cut = candidate.copy()
    cut[np.arange(h)[:, None] < line[None, :]] = 0
    return _touching_seeds(cut, info)


def _touching_seeds(mask: np.ndarray, info: dict) -> np.ndarray:
    """The 4-connected pieces of ``mask`` (uint8) that hold a pixel of a seed region (``info``'s
    ``labels``, ``sizes`` and ``seeds``), as a uint8 0/1 mask."""
    is_seed = np.zeros(info["sizes"].size, bool)
    is_seed[info["seeds"]] = True
    mask = (np.asarray(mask) > 0).astype(np.uint8)
    n, comp = cv2.connectedComponents(mask, connectivity=4)
    keep = np.zeros(n, np.uint8)
    keep[comp[np.take(is_seed, info["labels"]) & (mask > 0)]] = 1
    keep[0] = 0
    return np.take(keep, comp)


def _front_top(tops: np.ndarray) -> int:
    """The candidate's highest row as :func:`open_ground` takes it, from each column's top row."""
    return int(np.sort(tops)[int(FRONT_SPIKE * tops.size)])


def below_the_horizon(candidate: np.ndarray, info: dict) -> np.ndarray:
    """On open ground, drop the non-seed regions that end within the horizon band.

    The horizon band is the :data:`FRONT_BAND` of the height below the front's top row
    (:func:`open_ground`).  A region whose lowest pixel lies in it or above does not come down
    to the ground ahead: it is distant terrain standing above the horizon (hills, a treeline, a
    skyline of the ground's colour), not ground the robot can reach.  Then only what still
    touches a seed stays.  Without ``labels`` in ``info`` the candidate is returned as it is.
    """
    labels = info.get("labels")
    if labels is None:
        return candidate
    h, w = candidate.shape
    has = candidate.any(axis=0)
    band = _front_top(np.where(has, candidate.argmax(axis=0), h)) + FRONT_BAND * h
    k = info["sizes"].size
    drop = np.bincount(labels[int(math.ceil(band)):].ravel(), minlength=k) == 0   # no pixel below the band
    drop[info["seeds"]] = False
    kept = candidate.copy()
    kept[np.take(drop, labels)] = 0
    return _touching_seeds(kept, info)


#: Reasons :func:`abstain` gives for shrinking the mask (the reply's ``abstained``).
ABSTAIN_REASONS = ("seed not ground", "seed reaches the horizon", "dim seed")


def abstain(candidate: np.ndarray, info: dict, params: RoadParams) -> tuple[np.ndarray, float, str | None]:
    """Calibrated abstention: shrink the candidate mask to what the model is sure of when its seed is weak.

    A robot drives where the mask is green, so green where it cannot drive is the costly
    error.  Three signs say the seed cannot be trusted to extend:

    * **seed not ground**: no region of the bottom-centre cell has both ``seed_share`` of it and
      ground contact (the seeds are the fragments reaching the cell's lower half, see
      :func:`seed_regions`: leaf litter, or a vehicle, a wall, a trunk close ahead over them);
    * **seed reaches the horizon**: the road-like regions connected to the seed reach above
      ``reach`` of the height, so the seed's appearance also matches what stands on the
      ground (trunks, building bases, leaf litter against a hillside), a low-contrast seed;
      unless the candidate's upper edge is a horizon (:func:`open_ground`: open ground);
    * **dim seed**: the seed's mean grey level is below ``dim`` (dusk, night).

    Then the mask keeps only its rows below ``cap`` of the height (the ground just ahead);
    with ``standing`` (and ``info`` from :func:`classify`) it also drops the non-seed regions
    with most of their pixels above that row (walls, trunks, building bases standing on the
    ground) and keeps only what still touches a seed.  On a textured floor (leaf litter) no single region may cover enough of the cell, so a
    seed without ground contact shrinks the same way rather than emptying the mask.

    When the candidate reaches above ``reach`` but :func:`open_ground` says its upper edge is a
    horizon, it is not shrunk to ``cap``: only the regions standing above the horizon go
    (:func:`below_the_horizon`), then what lies above the horizon line :func:`open_ground` found
    (:func:`cut_above_horizon`, with ``info["horizon"]``), and ``info["open_ground"]`` is set
    (the caller's column fill then starts at each column's lowest candidate pixel).

    Returns
    -------
    mask : (h, w) uint8
        The candidate, shrunk when the seed is weak.
    confidence : float in [0, 1]
        1 for a strong seed; lower the further the candidate reaches above ``reach`` and the
        darker the seed is below ``dim``; 0 when the seed is not ground.  It is a score for
        ranking frames, not a probability (docs/ACCURACY.md reports the precision of the
        frames above and below 1).
    abstained : str or None
        One of :data:`ABSTAIN_REASONS` when the mask was shrunk, else None.
    """
    h = candidate.shape[0]
    rows = np.flatnonzero(candidate.any(axis=1))
    top = rows[0] / h if rows.size else 1.0
    reach_conf = 1.0 if params.reach <= 0 else float(min(1.0, top / params.reach))
    if reach_conf < 1.0 and open_ground(candidate, params.front, info.get("grad"), info):
        reach_conf = 1.0   # it reaches the horizon because the ground is open, not up a wall
        info["open_ground"] = True
    dim_conf = 1.0 if params.dim <= 0 else float(min(1.0, info["seed_grey"] / params.dim))
    confidence = min(reach_conf, dim_conf)
    if info["grounded"] and confidence >= 1.0:
        if info.get("open_ground"):
            candidate = below_the_horizon(candidate, info)
            if info.get("horizon") is not None:   # the line open_ground found (front_share)
                candidate = cut_above_horizon(candidate, info, info["horizon"])
        return candidate, 1.0, None
    if not info["grounded"]:
        confidence, reason = 0.0, ABSTAIN_REASONS[0]
    else:
        reason = ABSTAIN_REASONS[1] if reach_conf <= dim_conf else ABSTAIN_REASONS[2]
    row = int(params.cap * h)
    sure = candidate.copy()
    sure[:row] = 0
    labels = info.get("labels")
    if labels is not None and params.standing:
        # a region with most of its pixels above the sure rows stands on the ground (a wall, a
        # trunk, a building base; ground seen in perspective has most of its pixels low): it goes,
        # unless it is a seed; then only what still touches a seed stays
        total = info["sizes"]
        above = np.bincount(labels[:row].ravel(), minlength=total.size)
        drop = above * 2 > total
        drop[info["seeds"]] = False
        low, low_labels = sure[row:], labels[row:]   # the rows above are empty now
        low[np.take(drop, low_labels)] = 0
        n, comp = cv2.connectedComponents(low, connectivity=4)
        keep = np.zeros(n, np.uint8)
        keep[comp[np.isin(low_labels, info["seeds"]) & (low > 0)]] = 1
        keep[0] = 0
        sure[row:] = np.take(keep, comp)
    return sure, confidence, reason


#: The shortest ``boundary`` accepted (a share of the height; below it the Hough transform's vote
#: threshold falls to a few pixels and texture makes edges).
BOUNDARY_MIN_LENGTH = 0.1
#: :func:`cut_at_boundaries`' fixed geometry (chosen on the synthetic scenes and the edges of a few
#: shared frames by eye in the prototype of 2026-11-29, not by the cross-validation, which chooses
#: only ``boundary``; docs/ACCURACY.md): Canny's hysteresis thresholds on the grey working frame ...
BOUNDARY_CANNY = (75, 150)
#: ... a straight edge's angle from the horizontal, in degrees (a road's edge seen in perspective
#: runs up the frame; a shadow's far edge or a car's bottom runs across it, a pole or a trunk
#: stands upright) ...
BOUNDARY_ANGLES = (15.0, 75.0)
#: ... the Hough transform's angle step, in degrees ...
BOUNDARY_THETA = 2.0
#: ... the longest gap (working pixels) inside one straight edge ...
BOUNDARY_GAP = 2
#: ... the share of the edge's pixels within 2 px of the candidate (the edge runs through it) ...
BOUNDARY_INSIDE = 0.8
#: ... the distances (working pixels) of the strips sampled on each side of the edge ...
BOUNDARY_SIDES = (2, 3, 4, 5, 6)
#: ... at least this many candidate pixels in each side's strips ...
BOUNDARY_MIN_SIDE = 10
#: ... the two sides' mean chromaticities (R, G, B over their sum) at least this far apart (L1):
#: two materials, not the asphalt on both sides of a painted lane line (KITTI's: 0.006-0.008).
#: 0.02 by eye in the prototype; 0.015 since a sweep on the 60 labelled images (2026-11-29,
#: in-sample mean IoU 0.8095 / 0.8201 / 0.8275 / 0.8297 / 0.8290 / 0.8290 at 0 / 0.005 / 0.01 /
#: 0.015 / 0.018 / 0.02: below 0.015 lane lines and shadows start to cut), the lowest floor of
#: the flat top, which also cuts the synthetic structured road's seed 2 verge (0.019) ...
BOUNDARY_CHROMA = 0.015
#: ... and their mean features (log R/G, log B/G, log brightness) at least this far apart once
#: the move along :data:`SHADE_DIRECTION` is taken out (a shadow's edge up the frame moves them
#: along it: one surface in sun and shade) ...
BOUNDARY_MATERIAL = 0.015
#: ... and one edge never cuts more than this share of the candidate (the robot's side is the
#: larger: a boundary bounds the road, it does not halve it).
BOUNDARY_MAX_CUT = 0.5


def straight_edges(small: np.ndarray, candidate: np.ndarray, length: float) -> np.ndarray:
    """The straight edges of a working frame below the candidate's top, (n, 4) int ``x1, y1, x2, y2``.

    Canny (:data:`BOUNDARY_CANNY`) on the grey frame, its edges from 2 rows above the candidate's
    top row down (a boundary runs through the candidate; the rows above are up to half the work), then
    OpenCV's probabilistic Hough transform at :data:`BOUNDARY_THETA` (a fixed seed: the same
    input gives the same edges): at least ``length`` of the height along x or y, gaps up to
    :data:`BOUNDARY_GAP`, at least 0.6 x that length of votes.
    """
    h = small.shape[0]
    rows = np.flatnonzero(candidate.any(axis=1))
    if not rows.size:
        return np.zeros((0, 4), int)
    grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(grey, *BOUNDARY_CANNY)
    edges[:max(int(rows[0]) - 2, 0)] = 0
    lines = cv2.HoughLinesP(edges, 1, math.radians(BOUNDARY_THETA), threshold=int(length * h * 0.6),
                            minLineLength=int(length * h), maxLineGap=BOUNDARY_GAP)
    return np.zeros((0, 4), int) if lines is None else lines.reshape(-1, 4).astype(int)


def boundary_lines(candidate: np.ndarray, small: np.ndarray, length: float,
                   edges: np.ndarray | None = None) -> list[dict]:
    """The straight edges :func:`cut_at_boundaries` may cut along, before the cut-size test.

    Returns, per edge of :func:`straight_edges` (``edges``, computed when not given) whose angle
    lies in :data:`BOUNDARY_ANGLES` and which runs through the candidate
    (:data:`BOUNDARY_INSIDE` of its pixels within 2 px of it), with at least
    :data:`BOUNDARY_MIN_SIDE` candidate pixels in each side's strips (:data:`BOUNDARY_SIDES`), a
    dict: ``line`` (x1, y1, x2, y2), ``chroma`` (the L1 distance of the two sides' mean
    chromaticities), ``material`` (the distance of their mean features with the move along
    :data:`SHADE_DIRECTION` taken out) and ``boundary`` (both at least their floors).
    """
    from scmr_mesh.imaging._aot import boundary_sides_kernel

    if edges is None:
        edges = straight_edges(small, candidate, length)
    if not len(edges):
        return []
    dx = np.abs(edges[:, 2] - edges[:, 0])
    dy = np.abs(edges[:, 3] - edges[:, 1])
    angle = np.degrees(np.arctan2(dy, dx))
    keep = (angle >= BOUNDARY_ANGLES[0]) & (angle <= BOUNDARY_ANGLES[1])
    if not keep.any():
        return []
    lines = np.ascontiguousarray(edges[keep], dtype=np.int64)
    m = boundary_sides_kernel(lines, np.ascontiguousarray(candidate, dtype=np.uint8), np.ascontiguousarray(small),
                              _SIDE_D,
                              float(FEATURE_OFFSET))
    shade = SHADE_DIRECTION[:3] / np.linalg.norm(SHADE_DIRECTION[:3])
    out = []
    for line, row in zip(lines, m):
        if row[0] < BOUNDARY_INSIDE or min(row[1], row[5]) < BOUNDARY_MIN_SIDE:
            continue
        c0, c1 = row[9:12], row[12:15]
        chroma = float(np.abs(c0 / max(c0.sum(), 1e-9) - c1 / max(c1.sum(), 1e-9)).sum())
        dv = row[2:5] - row[6:9]
        material = float(np.linalg.norm(dv - dv.dot(shade) * shade))
        out.append({"line": tuple(int(v) for v in line), "chroma": chroma, "material": material,
                    "boundary": chroma >= BOUNDARY_CHROMA and material >= BOUNDARY_MATERIAL})
    return out


_SIDE_D = np.array(BOUNDARY_SIDES, np.float64)


def cut_at_boundaries(candidate: np.ndarray, small: np.ndarray, length: float,
                      edges: np.ndarray | None = None) -> tuple[np.ndarray, list[tuple]]:
    """Cut the candidate along the road's boundaries; keep the robot's side.

    Two surfaces of much the same colour, the asphalt and a pavement, a verge or a tunnel's wall,
    can pass one road model (one SRM region, or regions joined), and the column fill then paints
    the pavement green up to the buildings.  Between them runs a long straight edge up the frame
    in perspective: a kerb, a painted edge line, a wall's foot.  Each edge of
    :func:`boundary_lines` with two different materials on its sides (``boundary``) cuts the
    candidate: what lies on the far side of its line (extended across the frame) from the
    bottom-centre pixel, the robot, is dropped, unless that is more than :data:`BOUNDARY_MAX_CUT`
    of the candidate.  A painted lane line has asphalt on both sides and a shadow's edge one
    surface in sun and shade, so neither cuts.  What the cuts detach from the bottom-centre cell
    the seeds come from goes too; pieces that were apart from it before the cut stay.

    ``edges``: :func:`straight_edges` of ``small`` for ``length``, computed when not given.
    Returns the candidate (the input itself when nothing was cut, else uint8 0/1) and the lines cut along.
    """
    from scmr_mesh.imaging._aot import boundary_cut_kernel

    if length <= 0 or not candidate.any():
        return candidate, []
    cand = (candidate != 0).astype(np.uint8)
    found = [f["line"] for f in boundary_lines(cand, small, length, edges) if f["boundary"]]
    if not found:
        return candidate, []
    cut, did = boundary_cut_kernel(cand, np.array(found, np.int64), float(BOUNDARY_MAX_CUT))
    used = [line for line, d in zip(found, did) if d]
    if not used:
        return candidate, []
    return _drop_detached(cand, cut), used


#: :func:`cut_rough`'s fixed geometry (chosen by eye in the prototype of 2026-11-29 on the shared
#: frames, not by the cross-validation, which chooses only ``rough``; docs/ACCURACY.md): the box
#: (300x225 frame pixels) the absolute Laplacian is averaged over ...
ROUGH_BOX = 5
#: ... the grey levels above the candidate's median in its row that count: brighter is clipped
#: (paint: a lane line, a box junction's hatching or a cycle lane's symbol is bright and thin, and
#: unclipped its edges read as rough) ...
ROUGH_PAINT = 10
#: ... the opening (working pixels) that leaves only rough *surfaces* (not the rim of a car, a
#: wheel or a single stone) ...
ROUGH_OPEN = 5
#: ... and the fewest working pixels of one rough surface (0.6 % of the frame).
ROUGH_MIN_AREA = 100
#: A row's median is taken over at least this many candidate pixels (fewer: the row is not judged).
ROUGH_MIN_ROW = 10
#: The robot's path: the working frame's centre column and this many on each side (11 of 150).  A
#: rough surface reaching into it is driven on, never cut (a cobbled stretch ahead, a gravel strip
#: under the robot, a band across the road: a hostile review's scenes, 2026-11-29).  Up to 8 it
#: leaves every shared frame's cut as it is; at 12 KITTI semantics 000004's pavement reaches it.
ROUGH_PATH = 5
#: A rough surface is cut only where it reaches the working frame's bottom this many rows (a
#: pavement or a verge runs beside the robot from where it stands; a band across the road ahead
#: does not: the review's diagonal band, beside the path in part, took the road beyond it, IoU
#: 0.993 -> 0.697).  At 12 the shared frames keep their gains but CamVid Seq05VD 450's (0.019),
#: whose pavement starts 19 rows up (2026-11-29).
ROUGH_BESIDE = 12
#: ... and only where no more than this many times its area of smooth candidate lies beyond it
#: (above it, in its columns): the road goes on beyond a band across it, not beyond a pavement.
#: With ROUGH_BESIDE alone 106 of 264 bands across the road (5 heights, 4 slopes, 3 widths,
#: 2 seeds) lost more than 0.02 IoU; with both, none; at 1.5 KITTI road's gain (0.016) goes too.
ROUGH_BEYOND = 2.0
#: The blur guard (issue 27, 2026-11-29, closing session; docs/ACCURACY.md).  Blur over part of the
#: frame (a water drop, mud, motion blur on part of the lens) lowers the fine texture of the road
#: under it, and the sharp road beside it reads as rough.  Sharpness is measured apart from how
#: much texture a surface has: the sum of |Laplacian| over the sum of |Sobel gradient| (3x3) of
#: the 300x225 frame in grey, which a blur of scale s lowers about as 1/s whatever the contrast.
#: Over the frame it is taken per block of this size (the frame's 6 x 5 blocks) ...
ROUGH_BLUR_BLOCK = (50, 45)
#: ... over the blocks whose mean gradient is at least this (sky and flat walls hold only noise) ...
ROUGH_BLUR_EDGES = 8.0
#: ... (fewer than this many such blocks: no judgement) ...
ROUGH_BLUR_MIN_BLOCKS = 4
#: ... and when the 90th percentile of the blocks' sharpness is more than this x the 10th, part of
#: the frame is blurred and nothing is cut.  The 60 shared frames measure 1.26-2.27 (median 1.56);
#: with a third to 60 % of the frame blurred at sigma 1.2 (a side, the centre, a disc over the
#: bottom centre) 2.49-6.14; at sigma 0.7, 1.70-3.88.  2.0 with ROUGH_SHARPER left every shared
#: frame's cut as it was and none of the second review's transforms worse on average than the cut
#: off; a third review found blurs both halves miss (a strong drop over the bottom centre, whose
#: blocks fall under ROUGH_BLUR_EDGES), which is why ``rough`` is off by default.
ROUGH_BLUR_SPREAD = 2.0
#: A rough surface whose sharpness is more than this x that of the smooth candidate in its rows
#: is the road beside a blur, not another material, and is not cut (the shared frames' cut
#: surfaces measure 1.00-1.32; the sharp road beside a blur mostly 1.5-3.7) ...
ROUGH_SHARPER = 1.4
#: ... judged only against at least this many smooth candidate pixels in its rows (fewer: it is cut).
ROUGH_SHARPER_MIN = 50


def _row_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per row, the median of ``values`` (uint8) over ``mask`` (bool or uint8): np.median's value, NaN where
    fewer than :data:`ROUGH_MIN_ROW` pixels (a compiled counting pass: 0.02 ms on the working frame,
    np.nanmedian's 0.45 ms)."""
    from scmr_mesh.imaging._aot import row_medians_kernel

    return row_medians_kernel(np.ascontiguousarray(values, dtype=np.uint8),
                              np.ascontiguousarray(mask).view(np.uint8), ROUGH_MIN_ROW)


def rough_surface(candidate: np.ndarray, small: np.ndarray, frame: np.ndarray, ratio: float) -> np.ndarray:
    """The candidate's rough surfaces: cobbles, paving slabs, gravel, leaf litter beside smooth asphalt.

    Texture is the absolute Laplacian of the 300x225 frame (``frame``, RGB uint8) in grey, averaged
    over a :data:`ROUGH_BOX` box and sampled at the working pixels' centres; before it, every grey
    level more than :data:`ROUGH_PAINT` above the candidate's median in its row of the working
    frame (``small``, RGB) is clipped to that, so bright paint on the road adds no texture.  A
    candidate pixel is rough when its texture is more than ``ratio`` x the candidate's median
    texture in its row (at least 1): the comparison is made at one distance from the camera, so
    perspective, which shrinks the texture of the far road, does not enter.  A row with fewer
    than :data:`ROUGH_MIN_ROW` candidate pixels is not judged.  An opening (:data:`ROUGH_OPEN`)
    and a least area (:data:`ROUGH_MIN_AREA`) keep the surfaces, not the rims and spots; a
    surface reaching into the robot's path (:data:`ROUGH_PATH`) is ground it drives on and is
    never rough, nor is one that does not reach the bottom :data:`ROUGH_BESIDE` rows (it lies
    ahead, not beside), nor one with more than :data:`ROUGH_BEYOND` x its area of smooth
    candidate beyond it (a band across the road): only surfaces beside the path from where the
    robot stands, with no road beyond them, are.  Last, the blur guard (:func:`_spare_the_sharp`)
    keeps what blur over part of the frame made rough: nothing is, when the frame's sharpness is
    uneven (:func:`blur_spread` above :data:`ROUGH_BLUR_SPREAD`), nor a surface sharper than the
    smooth road in its rows (:data:`ROUGH_SHARPER`).  Only the frame's rows from the first judged
    row down are read for texture.  Returns a bool mask of the working frame (0.1-0.2 ms; 0.5 ms
    more when a surface is found, for the guard).
    """
    from scmr_mesh.imaging._aot import rough_rows_kernel

    wh, ww = candidate.shape
    fh, fw = frame.shape[:2]
    if (fh, fw) != (2 * wh + 1, 2 * ww) or small.shape[:2] != (wh, ww):
        raise ValueError(f"rough_surface reads the 300x225 frame of a 150x112 working frame; got a frame of "
                         f"{fw}x{fh}, a working frame of {small.shape[1]}x{small.shape[0]} and a candidate of {ww}x{wh}")
    out = np.zeros((wh, ww), bool)
    mask = (candidate != 0).view(np.uint8)
    med = _row_medians(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), mask)
    judged = np.flatnonzero(np.isfinite(med))
    if not judged.size:
        return out
    w0 = int(judged[0])   # the rows above hold too little candidate to judge
    top = np.where(np.isfinite(med[w0:]), np.minimum(med[w0:] + ROUGH_PAINT, 255), 255).astype(np.uint8)
    # the frame rows nearest the working rows' centres; the texture is read from the frame's rows
    # from the box's and the Laplacian's reach above the first of them
    centre = (np.arange(w0, wh) * fh + fh // 2) // wh
    f0 = max(int(centre[0]) - ROUGH_BOX // 2 - 1, 0)
    grey = cv2.cvtColor(frame[f0:], cv2.COLOR_RGB2GRAY)
    # each frame row is clipped at its working row's ceiling (the rows above w0 at w0's)
    clipped = np.minimum(grey, top[np.maximum(np.arange(f0, fh) * wh // fh - w0, 0)][:, None])
    lap = cv2.convertScaleAbs(cv2.Laplacian(clipped, cv2.CV_16S, ksize=1))
    # the box averages the 5x5 around each working pixel's 2x2 of frame pixels: it is sampled
    texture = cv2.blur(lap, (ROUGH_BOX, ROUGH_BOX))[centre - f0][:, fw // ww // 2::fw // ww]
    rough, count = rough_rows_kernel(np.ascontiguousarray(texture), np.ascontiguousarray(mask[w0:]),
                                     float(ratio), ROUGH_MIN_ROW)
    if count < ROUGH_MIN_AREA:   # the opening only shrinks
        return out
    kernel = np.ones((ROUGH_OPEN, ROUGH_OPEN), np.uint8)
    core = cv2.erode(rough, kernel)
    if cv2.countNonZero(core) == 0:   # no ROUGH_OPEN square is all rough: the opening is empty
        return out
    rough = cv2.dilate(core, kernel)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(rough, connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] >= ROUGH_MIN_AREA
    big[0] = False
    full = np.zeros((wh, ww), lab.dtype)
    full[w0:] = lab
    # a rough surface in the robot's path (crossing the frame's centre columns: a cobbled stretch
    # ahead, a gravel strip under the robot, a band across the road) is ground it drives on, rough
    # or not; only what lies wholly beside the path is another material (a pavement, a verge)
    path = full[:, ww // 2 - ROUGH_PATH: ww // 2 + ROUGH_PATH + 1]
    big[np.unique(path)] = False
    # ... and a pavement or a verge runs beside the robot from where it stands: a rough surface
    # that does not reach the frame's bottom rows lies ahead (a band across the road, seen at an
    # angle, beside the path only in part), and cutting it would take the road beyond it too
    lowest = w0 + stats[:, cv2.CC_STAT_TOP] + stats[:, cv2.CC_STAT_HEIGHT] - 1
    big[lowest < wh - ROUGH_BESIDE] = False
    # ... and no more smooth candidate lies beyond it (above it in its columns) than
    # ROUGH_BEYOND x its area: the road goes on beyond a band across it, not beyond a pavement
    if big.any():
        above = np.cumsum((mask != 0) & (full == 0), axis=0, dtype=np.int32)
        for k in np.flatnonzero(big):
            blob = full == k
            cols = np.flatnonzero(blob.any(axis=0))
            tops = np.argmax(blob[:, cols], axis=0)
            beyond = int(np.where(tops > 0, above[np.maximum(tops - 1, 0), cols], 0).sum())
            if beyond > ROUGH_BEYOND * stats[k, cv2.CC_STAT_AREA]:
                big[k] = False
    if big.any():
        _spare_the_sharp(big, full, mask, frame)
    out[w0:] = np.take(big, lab)
    return out


def sharpness_maps(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|Laplacian| (4-neighbour) and |Sobel x| + |Sobel y| (3x3) of the 300x225 frame in grey, float32."""
    grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY).astype(np.float32)
    lap = np.abs(cv2.Laplacian(grey, cv2.CV_32F, ksize=1))
    grad = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)) + np.abs(cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    return lap, grad


def blur_spread(lap: np.ndarray, grad: np.ndarray) -> float:
    """How unevenly sharp the frame is: the 90th over the 10th percentile of its blocks' sharpness.

    Per :data:`ROUGH_BLUR_BLOCK` block with a mean gradient of at least :data:`ROUGH_BLUR_EDGES`,
    sum |Laplacian| / sum |gradient| (:func:`sharpness_maps`); 1.0 with fewer than
    :data:`ROUGH_BLUR_MIN_BLOCKS` such blocks.  A frame in one focus measures about 1.3-2.3; a
    frame with part of it blurred more (:data:`ROUGH_BLUR_SPREAD`).
    """
    bw, bh = ROUGH_BLUR_BLOCK
    h, w = lap.shape
    nx, ny = w // bw, h // bh
    if nx < 1 or ny < 1:
        return 1.0
    # INTER_AREA at an integer factor: each block's mean
    lap_b = cv2.resize(lap[:ny * bh, :nx * bw], (nx, ny), interpolation=cv2.INTER_AREA)
    grad_b = cv2.resize(grad[:ny * bh, :nx * bw], (nx, ny), interpolation=cv2.INTER_AREA)
    edged = grad_b >= ROUGH_BLUR_EDGES
    if int(edged.sum()) < ROUGH_BLUR_MIN_BLOCKS:
        return 1.0
    sharp = lap_b[edged] / grad_b[edged]
    hi, lo = float(np.percentile(sharp, 90)), float(np.percentile(sharp, 10))
    if hi <= 0:   # no block has any curvature (ramps only): evenly unsharp
        return 1.0
    if lo <= 0:   # a block that is a pure ramp beside sharp ones: as uneven as can be
        return math.inf
    return hi / lo


def _spare_the_sharp(big: np.ndarray, full: np.ndarray, mask: np.ndarray, frame: np.ndarray) -> None:
    """The blur guard: clear ``big`` (per label of ``full``, the rough surfaces found) where blur, not
    material, made them rough.  All when the frame is unevenly sharp (:func:`blur_spread` above
    :data:`ROUGH_BLUR_SPREAD`); else each surface more than :data:`ROUGH_SHARPER` x as sharp as the
    smooth candidate (``mask`` less the surfaces) in its rows."""
    lap, grad = sharpness_maps(frame)
    if blur_spread(lap, grad) > ROUGH_BLUR_SPREAD:
        big[:] = False
        return
    wh, ww = full.shape
    lap_w = cv2.resize(lap, (ww, wh), interpolation=cv2.INTER_AREA)
    grad_w = cv2.resize(grad, (ww, wh), interpolation=cv2.INTER_AREA)
    found = np.take(big, full)
    smooth = (mask != 0) & ~found
    for k in np.flatnonzero(big):
        blob = full == k
        rows = np.flatnonzero(blob.any(axis=1))
        band = slice(int(rows[0]), int(rows[-1]) + 1)   # the surface's rows
        rest = smooth[band]   # the smooth candidate in them
        if int(rest.sum()) < ROUGH_SHARPER_MIN:
            continue
        mine = float(lap_w[blob].sum()) / max(float(grad_w[blob].sum()), 1e-6)
        beside = float(lap_w[band][rest].sum()) / max(float(grad_w[band][rest].sum()), 1e-6)
        if mine > ROUGH_SHARPER * max(beside, 1e-6):
            big[k] = False


def cut_rough(candidate: np.ndarray, small: np.ndarray, frame: np.ndarray, ratio: float) -> np.ndarray:
    """Cut the candidate's rough surfaces (:func:`rough_surface`) and what they detach from the robot.

    SRM joins a pavement of cobbles or slabs, or a leaf-littered verge, to the asphalt when their
    mean colours agree; their texture does not.  What the cut detaches from the bottom-centre cell
    the seeds come from goes too; pieces that were apart from it before stay (as in
    :func:`cut_at_boundaries`).  ``frame``: the 300x225 RGB frame ``small`` was made from.
    Returns the input itself when nothing was cut, else uint8 0/1.
    """
    if ratio <= 0 or not candidate.any():
        return candidate
    rough = rough_surface(candidate, small, frame, ratio)
    if not rough.any():
        return candidate
    cand = (candidate != 0).astype(np.uint8)
    cut = cand.copy()
    cut[rough] = 0
    return _drop_detached(cand, cut)


def _drop_detached(before: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """``cut`` (uint8 0/1, changed in place and returned) less what a cut detached from the robot's
    side: the pieces that no longer touch the seeds' bottom-centre cell but were connected to it in
    ``before``.  Pieces already apart from it stay, as they do in a frame without a cut (the carried
    model's candidate may not touch the cell at all: a box over it)."""
    comp0, robot0 = _touching_the_cell(before)
    comp, robot = _touching_the_cell(cut)
    cut[(cut > 0) & ~np.take(robot, comp) & np.take(robot0, comp0)] = 0
    return cut


def _touching_the_cell(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mask``'s 4-connected components and, per component, whether it reaches the bottom-centre
    cell the seeds come from (:func:`~scmr_mesh.imaging.steps.bottom_centre` of the lower half)."""
    n, comp = cv2.connectedComponents(mask, connectivity=4)
    reaches = np.zeros(n, bool)
    reaches[np.unique(bottom_centre(roi(comp)))] = True
    reaches[0] = False
    return comp, reaches
