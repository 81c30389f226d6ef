"""The ``best`` mode: a road model learned from each frame itself (self-supervised).

No constant in here was fitted to the evaluation images' labels by hand: the
few that remain (:class:`RoadParams`) are chosen by leave-one-dataset-out
cross-validation (:func:`scmr_mesh.imaging.evaluate.cross_validate`, ``scmr
eval --cv``), and docs/ACCURACY.md reports the cross-validated scores beside
the in-sample ones.

Steps, on the blurred 300x225 frame:

1. **Regions.**  SRM (Q = 16 x q = 512) on the frame put through a power-law tone curve
   ``255 (v / 255) ** gamma`` (gamma = 0.35): SRM's merge bound is in absolute
   grey levels, so in a dark frame the road, the pavement and the building
   bases differ by less than the bound and merge; on a perceptual scale they
   do not (Weber's law).
2. **Self-supervised seeds.**  The regions that cover at least ``seed_share``
   of the thesis's bottom-centre cell (rows 83-100 %, columns 33-67 %) are
   taken to be road, as Stanley's vision system took the patch the laser
   scanners had found drivable (Dahlkamp et al. 2006).
3. **A per-frame appearance model.**  Each seed region gives one Gaussian
   (mean and covariance of its pixels) over four pixel features: two
   log-chromaticities ``log(R/G)``, ``log(B/G)`` (unchanged by the
   illuminant's brightness: Alvarez et al.'s illuminant-invariant idea), the
   log-brightness, and log texture (Sobel magnitude).  The mixture of the
   seeds' Gaussians is the road model (Dahlkamp et al. keep several road
   Gaussians for the same reason: shade, puddles, wheel tracks).
4. **Classification.**  A region is road-like when its mean feature vector
   lies inside the ``p``-quantile ellipsoid (chi-square with 4 degrees of
   freedom) of some seed Gaussian; a small isotropic ``noise`` term keeps a
   nearly uniform seed from rejecting everything.
5. **Geometry.**  Rows above ``horizon`` of the height are dropped; only
   road-like pixels 4-connected to the bottom-centre cell stay; a bottom-up
   column fill bridges gaps of up to ``gap`` pixels (lane markings).

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

import cv2
import numpy as np

from scmr_mesh.errors import InputError


@dataclass(frozen=True)
class RoadParams:
    """The constants of the self-supervised road model (defaults: chosen by cross-validation).

    Attributes
    ----------
    gamma : float
        Tone curve exponent of SRM's input (1 = linear).
    seed_share : float
        A region seeds the road model when it covers this share of the bottom-centre cell.
    p : float
        Quantile of the chi-square(4) ellipsoid around a seed Gaussian that counts as road-like.
    noise : float
        Isotropic standard deviation added to every seed covariance (feature units).
    horizon : float
        Rows above this fraction of the height are never drivable (0 = no prior).
    gap : int
        Longest run of non-road pixels the column fill bridges.
    """

    gamma: float = 0.35
    seed_share: float = 0.10
    p: float = 0.95
    noise: float = 0.02
    horizon: float = 0.5
    gap: int = 20

    def check(self) -> RoadParams:
        if not 0 < self.gamma <= 4:
            raise InputError(f"gamma must be in (0, 4], got {self.gamma}")
        if not 0 < self.seed_share <= 1:
            raise InputError(f"seed_share must be in (0, 1], got {self.seed_share}")
        if not 0 < self.p < 1:
            raise InputError(f"p must be in (0, 1), got {self.p}")
        if not self.noise > 0:
            raise InputError(f"noise must be > 0, got {self.noise}")
        if not 0 <= self.horizon < 1:
            raise InputError(f"horizon must be in [0, 1), got {self.horizon}")
        if int(self.gap) < 0:
            raise InputError(f"gap must be >= 0, got {self.gap}")
        return self

    def as_dict(self) -> dict:
        return asdict(self)


#: Feature offset (grey levels) inside the logarithms: the sensor noise floor,
#: so a near-black pixel's chromaticity does not explode.
FEATURE_OFFSET = 10.0
N_FEATURES = 4


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


_CHI2: dict = {}


def classify(blurred: np.ndarray, seg, params: RoadParams) -> tuple[np.ndarray, dict]:
    """Candidate road pixels of a frame from its SRM regions (steps 2-5 before the column fill).

    Parameters
    ----------
    blurred : (H, W, 3) uint8
        The blurred frame (features are measured on it, not on the tone-mapped one).
    seg : SrmResult
        SRM of the tone-mapped frame.
    params : RoadParams

    Returns
    -------
    candidate : (H, W) uint8
        1 = road-like and connected to the bottom-centre cell.
    info : dict
        ``seeds`` (region labels), ``road_regions`` (count).
    """
    from scmr_mesh.imaging._aot import region_features_kernel
    from scmr_mesh.imaging.steps import bottom_centre, roi

    labels = seg.labels
    h, w = labels.shape
    k = seg.n_regions
    cell = bottom_centre(roi(labels))
    counts = np.bincount(cell.ravel(), minlength=k)
    seeds = np.flatnonzero(counts >= params.seed_share * cell.size)
    if seeds.size == 0:
        seeds = np.array([int(np.argmax(counts))])
    slot = np.full(k, -1, np.int32)
    slot[seeds] = np.arange(seeds.size, dtype=np.int32)
    grey = cv2.cvtColor(blurred, cv2.COLOR_RGB2GRAY).astype(np.float32)
    grad = cv2.magnitude(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    sums, m1, m2, ns = region_features_kernel(labels, blurred, grad, slot, int(k), FEATURE_OFFSET)
    means = sums[:, :N_FEATURES] / np.maximum(sums[:, N_FEATURES:], 1.0)
    limit = _CHI2.get(params.p)
    if limit is None:
        limit = _CHI2[params.p] = chi2_quantile(params.p, N_FEATURES)
    road = np.zeros(k, bool)
    floor = np.eye(N_FEATURES) * params.noise**2
    for j in range(seeds.size):
        n = ns[j]
        mu = m1[j] / n
        cov = (m2[j] - n * np.outer(mu, mu)) / (n - 1) if n > N_FEATURES else np.zeros((N_FEATURES, N_FEATURES))
        icov = np.linalg.inv(cov + floor)
        d = means - mu
        road |= ((d @ icov) * d).sum(axis=1) <= limit
    road[seeds] = True
    cand = road.astype(np.uint8)[labels]
    if params.horizon > 0:
        cand[: int(params.horizon * h)] = 0
    n_comp, comp = cv2.connectedComponents(cand, connectivity=4)
    hits = np.bincount(bottom_centre(roi(comp)).ravel(), minlength=n_comp)
    hits[0] = 0
    return (hits > 0).astype(np.uint8)[comp], {"seeds": seeds, "road_regions": int(road.sum())}
