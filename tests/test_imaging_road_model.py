"""The self-supervised road model of ``best`` (imaging/road_model.py) and its cross-validation."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from scmr_mesh.errors import InputError
from scmr_mesh.imaging import segment_drivable, srm
from scmr_mesh.imaging._srm_kernels import candidate_kernel, road_share_kernel
from scmr_mesh.imaging.codec import FRAME_SHAPE, load_frame
from scmr_mesh.imaging.evaluate import (
    choose_combination,
    cross_validate,
    evaluate,
    format_cv_table,
    load_manifest,
    score,
    synthetic_fits,
    synthetic_floor,
    synthetic_scores,
)
from scmr_mesh.imaging.pipeline import DEFAULT_PARAMS, working_frame
from scmr_mesh.imaging.road_model import (
    FEATURE_OFFSET,
    FULL_SHADE,
    SHADE_DIRECTION,
    WORK_SHAPE,
    RoadParams,
    _seeds_grounded,
    abstain,
    candidate_regions,
    chi2_quantile,
    classify,
    connected_to_seeds,
    feature_tables,
    below_the_horizon,
    cut_above_horizon,
    front_share,
    horizon_line,
    open_ground,
    same_surface,
    seed_regions,
    tone_curve,
)
from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene


@pytest.mark.parametrize("p,dof,want", [(0.95, 4, 9.487729), (0.99, 4, 13.276704), (0.95, 1, 3.841459),
                                        (0.5, 2, 2 * math.log(2)), (0.999, 3, 16.266236)])
def test_chi2_quantile_matches_tables(p, dof, want):
    assert chi2_quantile(p, dof) == pytest.approx(want, rel=1e-5)


def test_tone_curve_is_the_power_law():
    v = np.arange(256, dtype=np.uint8).reshape(16, 16)
    out = tone_curve(v, 0.5)
    assert out[0, 0] == 0 and out[-1, -1] == 255
    np.testing.assert_array_equal(out.ravel(), np.rint(255 * (np.arange(256) / 255) ** 0.5).astype(np.uint8))
    np.testing.assert_array_equal(tone_curve(v, 1.0), v)


def _slow_road_share(labels, img, grad, seeds, noise, limit, shade=0.0, sunlit=0.0):
    """The road model in plain numpy: per-pixel features, seed Gaussians, pixels inside some ellipsoid."""
    f = img.astype(np.float64) + FEATURE_OFFSET
    x = np.stack([np.log(f[..., 0] / f[..., 1]), np.log(f[..., 2] / f[..., 1]),
                  np.log(f.sum(axis=2) / 3.0), np.log1p(np.floor(np.clip(grad, 0, 2047).astype(np.float64) + 0.5) / 8.0)], axis=2).reshape(-1, 4)
    lab = labels.ravel()
    k = int(lab.max()) + 1
    mus, covs, hit = [], [], np.zeros(len(x), bool)
    for s in seeds:
        xs = x[lab == s]
        mu = xs.mean(0)
        cov = (np.cov(xs.T) if len(xs) > 4 else np.zeros((4, 4))) + noise**2 * np.eye(4)
        d = x - mu
        plain = np.linalg.inv(cov)
        q = np.einsum("ki,ij,kj->k", d, plain, d)
        if mu[2] >= math.log(sunlit + FEATURE_OFFSET):
            cov = cov + shade**2 * np.outer(SHADE_DIRECTION, SHADE_DIRECTION)
            # shade only darkens: the shade term counts on the shaded side of a sunlit seed only,
            # the side of v^T C0^-1 d (the most likely amount of shade given the seed's spread)
            shaded = np.einsum("ki,ij,kj->k", d, np.linalg.inv(cov), d)
            q = np.where(np.einsum("ki,ij,j->k", d, plain, SHADE_DIRECTION) < 0, q, shaded)
        mus.append(mu)
        covs.append(cov)
        hit |= q <= limit
    hit &= ~np.isin(lab, seeds)
    return np.bincount(lab, weights=hit, minlength=k), np.array(mus), np.array(covs)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), h=st.integers(2, 40), w=st.integers(2, 40), k=st.integers(1, 6),
       shade=st.sampled_from([0.0, 0.2, 1.0]), sunlit=st.sampled_from([0.0, 100.0, 255.0]))
@example(seed=0, h=2, w=2, k=5, shade=0.0, sunlit=0.0)  # 4 pixels cannot hold 5 labels (found by Hypothesis)
def test_road_share_kernel_equals_the_numpy_slow_path(seed, h, w, k, shade, sunlit):
    k = min(k, h * w)  # "every label present" needs a pixel per label
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    labels = rng.integers(0, k, (h, w)).astype(np.int32)
    labels.flat[:k] = np.arange(k)  # every label present
    grad = rng.random((h, w), dtype=np.float32) * 500
    seeds = np.unique(rng.integers(0, k, 2))
    slot = np.full(k, -1, np.int32)
    slot[seeds] = np.arange(seeds.size)
    limit = chi2_quantile(0.95, 4)
    tables = feature_tables(FEATURE_OFFSET)
    inside, mus, covs, chroma, gmed = road_share_kernel(labels, img, grad, slot, k, *tables, 0.02**2, limit,
                                                        SHADE_DIRECTION, shade**2, math.log(sunlit + FEATURE_OFFSET))
    want, wmus, wcovs = _slow_road_share(labels, img, grad, seeds, 0.02, limit, shade, sunlit)
    np.testing.assert_allclose(mus, wmus, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(covs, wcovs, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(inside, want)
    # the weak join's inputs: each region's mean chromaticity and log brightness, the seed pixels' median magnitude
    f = img.astype(np.float64) + FEATURE_OFFSET
    lab = labels.ravel()
    for c, want_c in enumerate((np.log(f[..., 0] / f[..., 1]), np.log(f[..., 2] / f[..., 1]),
                                np.log(f.sum(axis=2) / 3.0))):
        np.testing.assert_allclose(chroma[:, c], np.bincount(lab, weights=want_c.ravel(), minlength=k)
                                   / np.bincount(lab, minlength=k), rtol=1e-9, atol=1e-12)
    assert gmed == np.median(grad[np.isin(labels, seeds)].astype(np.float64))


def _rgb_of_features(a, b, c):
    """The RGB (uint8) whose features are log R/G = a, log B/G = b, log brightness = c (offsets included)."""
    g = 3.0 * math.exp(c) / (math.exp(a) + 1.0 + math.exp(b))
    return np.rint(np.array([g * math.exp(a), g, g * math.exp(b)]) - FEATURE_OFFSET).astype(np.uint8)


def test_a_seed_below_sunlit_joins_its_surface_under_more_sun_or_shade():
    """Analytic: a flat seed below ``sunlit`` with three regions above it across a weak border.  One
    is the seed's surface under more sun (features moved 0.8 against SHADE_DIRECTION: brighter,
    less blue), one under more shade (0.5 along it: darker, bluer), and one as bright as the first
    with its chromaticity moved the other way (bluer still).  The join's plain test (chromaticity
    within 2 sd of the seed's) takes none; the shade-line test takes the first two only; with
    ``shade_from`` below the seed's brightness the gate closes and none joins (only the gate: the
    covariances stay those of a seed below ``sunlit``); and the per-pixel test (road_share_kernel)
    takes none."""
    seed_rgb = np.array([60, 66, 78], np.uint8)
    ff = seed_rgb.astype(np.float64) + FEATURE_OFFSET
    seed_f = np.array([math.log(ff[0] / ff[1]), math.log(ff[2] / ff[1]), math.log(ff.sum() / 3)])
    sun = seed_f - 0.8 * SHADE_DIRECTION[:3]
    shade = seed_f + 0.5 * SHADE_DIRECTION[:3]
    wrong = seed_f.copy()
    wrong[2] = sun[2]
    wrong[:2] += 0.8 * SHADE_DIRECTION[:2]
    labels = np.full((30, 21), 4, np.int32)
    labels[10:20, :7] = 1
    labels[10:20, 7:14] = 2
    labels[10:20, 14:] = 3
    labels[20:] = 0
    img = np.zeros((30, 21, 3), np.uint8)
    img[labels == 0] = seed_rgb
    img[labels == 1] = _rgb_of_features(*sun)
    img[labels == 2] = _rgb_of_features(*wrong)
    img[labels == 3] = _rgb_of_features(*shade)
    img[labels == 4] = (120, 160, 220)
    grad = np.zeros((30, 21), np.float32)
    slot = np.array([0, -1, -1, -1, -1], np.int32)
    dim = math.log(120 + FEATURE_OFFSET)   # the seed (grey ~68) is below it
    inside, mus, covs, chroma, gmed = road_share_kernel(labels, img, grad, slot, 5, *feature_tables(FEATURE_OFFSET),
                                                        0.02**2, chi2_quantile(0.9, 4), SHADE_DIRECTION, 0.04, dim)
    assert inside.tolist() == [0, 0, 0, 0, 0]
    start = np.array([True, False, False, False, False])
    road = start.copy()
    args = (labels, grad, start, road, 5, chroma, gmed, mus, covs, 4.0, 2.0, 9.0, 0.6, SHADE_DIRECTION)
    joined = [True, True, False, True, False]
    inc, added = candidate_kernel(*args, dim, FULL_SHADE)
    assert inc.tolist() == joined and added.tolist() == [False, True, False, True, False]
    inc, added = candidate_kernel(*args, -1e9, FULL_SHADE)   # the gate: a seed counted as sunlit
    assert inc.tolist() == [True, False, False, False, False]
    want_inc, _ = _weak_join_reference(labels, img, grad, start, road, mus, covs, 4.0, 2.0, 9.0, 0.6, dim)
    assert want_inc.tolist() == joined


def test_the_shade_line_reaches_one_full_shadow_only():
    """Analytic: a bright seed below ``shade_from`` (grey ~205) and two darker regions on its shade
    line, 0.9 and 1.6 full-shadow units (:data:`FULL_SHADE` ~1.28) along SHADE_DIRECTION.  The
    first joins; the second is deeper in shade than shade makes anything and does not; with the
    bound lifted both join (so the second's colours are on the line, within rounding)."""
    seed_rgb = np.array([200, 205, 215], np.uint8)
    ff = seed_rgb.astype(np.float64) + FEATURE_OFFSET
    seed_f = np.array([math.log(ff[0] / ff[1]), math.log(ff[2] / ff[1]), math.log(ff.sum() / 3)])
    labels = np.full((30, 20), 3, np.int32)
    labels[10:20, :10] = 1
    labels[10:20, 10:] = 2
    labels[20:] = 0
    img = np.zeros((30, 20, 3), np.uint8)
    img[labels == 0] = seed_rgb
    img[labels == 1] = _rgb_of_features(*(seed_f + 0.9 * FULL_SHADE * SHADE_DIRECTION[:3]))
    img[labels == 2] = _rgb_of_features(*(seed_f + 1.6 * FULL_SHADE * SHADE_DIRECTION[:3]))
    img[labels == 3] = (120, 160, 220)
    grad = np.zeros((30, 20), np.float32)
    slot = np.array([0, -1, -1, -1], np.int32)
    dim = math.log(250 + FEATURE_OFFSET)
    _i, mus, covs, chroma, gmed = road_share_kernel(labels, img, grad, slot, 4, *feature_tables(FEATURE_OFFSET),
                                                    0.02**2, chi2_quantile(0.9, 4), SHADE_DIRECTION, 0.04, dim)
    start = np.array([True, False, False, False])
    args = (labels, grad, start, start.copy(), 4, chroma, gmed, mus, covs, 4.0, 2.0, 9.0, 0.6, SHADE_DIRECTION, dim)
    assert candidate_kernel(*args, FULL_SHADE)[0].tolist() == [True, True, False, False]
    assert candidate_kernel(*args, 1e9)[0].tolist() == [True, True, True, False]
    want, _ = _weak_join_reference(labels, img, grad, start, start.copy(), mus, covs, 4.0, 2.0, 9.0, 0.6, dim)
    assert want.tolist() == [True, True, False, False]


@pytest.mark.parametrize("grey_seed", [True, False])
def test_the_shade_term_counts_on_the_shaded_side_only(grey_seed):
    """Analytic: a flat sunlit seed, a region moved t along SHADE_DIRECTION (its shade) and one moved
    t against it (brighter and warmer, "more sun").  With the shade term (sd 0.2) the shade is inside
    the ellipsoid and the sunnier region is not (shade only darkens); a seed below ``sunlit`` gets no
    shade term, so neither is; and the carried model (RoadTrack) draws the same line.  A region a
    little sunnier than the seed (0.045 against the shade direction, distance about 5 of the limit
    7.8 without the term) is inside either way: the sunny side is the seed's own Gaussian, for a
    sunlit seed and a dim one alike (a kernel that penalised a dim seed's sunny side, found by the
    review, fails here)."""
    from scmr_mesh.imaging.road_track import RoadTrack

    seed_rgb = np.array([150, 140, 125], np.uint8)
    f = np.log(seed_rgb.astype(np.float64) + FEATURE_OFFSET)
    m = np.array([f[0] - f[1], f[2] - f[1], math.log(seed_rgb.astype(np.float64).sum() / 3 + FEATURE_OFFSET), 0.0])
    t = 0.3   # 1.5 sd of the shade term, 15 sd of the noise term
    shade_rgb = _rgb_of_features(*(m + t * SHADE_DIRECTION)[:3])
    sun_rgb = _rgb_of_features(*(m - t * SHADE_DIRECTION)[:3])
    near_rgb = _rgb_of_features(*(m - 0.045 * SHADE_DIRECTION)[:3])
    img = np.empty((16, 10, 3), np.uint8)
    labels = np.zeros((16, 10), np.int32)
    img[:4], img[4:8], img[8:12], img[12:] = seed_rgb, shade_rgb, sun_rgb, near_rgb
    labels[4:8], labels[8:12], labels[12:] = 1, 2, 3
    grad = np.zeros((16, 10), np.float32)
    slot = np.array([0, -1, -1, -1], np.int32)
    sunlit = 100.0 if grey_seed else 200.0   # the seed's grey level is about 140
    inside, mus, covs, _c, _g = road_share_kernel(labels, img, grad, slot, 4, *feature_tables(FEATURE_OFFSET),
                                                  0.02**2, chi2_quantile(0.9, 4), SHADE_DIRECTION, 0.2**2,
                                                  math.log(sunlit + FEATURE_OFFSET))
    want = [0, 40, 0, 40] if grey_seed else [0, 0, 0, 40]
    assert inside.tolist() == want
    want_slow, _m, _v = _slow_road_share(labels, img, grad, [0], 0.02, chi2_quantile(0.9, 4), 0.2, sunlit)
    assert want_slow.tolist() == want
    track = RoadTrack()
    track.mean, track.cov = mus[0], np.zeros((4, 4))
    params = RoadParams(shade=0.2, sunlit=sunlit)
    feats = np.array([m + t * SHADE_DIRECTION, m - t * SHADE_DIRECTION, m - 0.045 * SHADE_DIRECTION])
    assert track.inside(feats, 0.9, params).tolist() == ([True, False, True] if grey_seed else [False, False, True])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.9, 1.1]))
def test_the_one_sided_shade_term_is_continuous(seed, scale):
    """On the boundary between the sides (v^T C0^-1 d = 0) the tests with and without the shade term
    give the same distance (Sherman-Morrison), so a pixel just across it gets the same answer: with
    an anisotropic seed (brightness spread 5x the chromaticity's, as on real roads) a point on the
    boundary at 0.9 (1.1) x the limit is inside (outside) on both sides.  And nothing jumps at the
    plain plane d . v = 0: a point there whose distances without and with the shade term straddle
    the limit gets one answer on both sides of it, which cutting by the sign of d . v does not
    (the review's reproducer: q 16.1 on one side, 7.6 on the other)."""
    from scmr_mesh.imaging.road_track import RoadTrack

    rng = np.random.default_rng(seed)
    a = rng.normal(size=(4, 4)) * np.array([0.03, 0.03, 0.15, 0.3])
    cov0 = a @ a.T + np.diag([0.03, 0.03, 0.15, 0.3]) ** 2
    params = RoadParams(shade=0.2, sunlit=0.0)
    track = RoadTrack()
    track.mean, track.cov = np.array([0.0, 0.0, 5.0, 1.0]), cov0
    c0 = cov0 + params.noise**2 * np.eye(4)
    w = np.linalg.solve(c0, SHADE_DIRECTION)
    d = rng.normal(size=4)
    d -= (d @ w) / (w @ w) * w   # on the boundary
    q0 = d @ np.linalg.solve(c0, d)
    d *= math.sqrt(scale * chi2_quantile(0.9, 4) / q0)
    eps = 1e-9 / math.sqrt(w @ w)
    got = track.inside(np.array([track.mean + d + eps * w, track.mean + d - eps * w]), 0.9, params)
    assert got.tolist() == [scale < 1, scale < 1]
    cs = c0 + params.shade**2 * np.outer(SHADE_DIRECTION, SHADE_DIRECTION)
    e = rng.normal(size=4)
    e -= (e @ SHADE_DIRECTION) * SHADE_DIRECTION   # on the plain plane (SHADE_DIRECTION is a unit vector)
    q0, qs = e @ np.linalg.solve(c0, e), e @ np.linalg.solve(cs, e)
    if qs < 0.9 * q0 and abs(e @ w) > 1e-6 * math.sqrt(e @ e) * math.sqrt(w @ w):
        e *= math.sqrt(chi2_quantile(0.9, 4) / math.sqrt(q0 * qs))   # q0 above the limit, qs below
        got = track.inside(np.array([track.mean + e + 1e-9 * SHADE_DIRECTION,
                                     track.mean + e - 1e-9 * SHADE_DIRECTION]), 0.9, params)
        assert got[0] == got[1]


def _region_labels(rng, h, w, n_colours, block):
    """Random 4-connected regions (as SRM makes them): the 4-components of a blocky random image."""
    small = rng.integers(0, n_colours, (max(1, h // block), max(1, w // block))).astype(np.uint8)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    labels = np.zeros((h, w), np.int32)
    n = 0
    for c in range(n_colours):
        m, comp = cv2.connectedComponents((img == c).astype(np.uint8), connectivity=4)
        sel = comp > 0
        labels[sel] = comp[sel] - 1 + n
        n += m - 1
    return labels, n


def _region_means(labels, img, k):
    """Each region's mean features log R/G, log B/G, log brightness (the join's ``chroma``, (k, 3))."""
    f = img.astype(np.float64) + FEATURE_OFFSET
    lab = labels.ravel()
    n = np.bincount(lab, minlength=k)
    feats = (np.log(f[..., 0] / f[..., 1]), np.log(f[..., 2] / f[..., 1]), np.log(f.sum(axis=2) / 3.0))
    return np.stack([np.bincount(lab, weights=x.ravel(), minlength=k) / n for x in feats], 1)


def _weak_join_reference(labels, img, grad, start, road, mus, covs, weak, chroma_lim, top_min, across,
                         shade_from, full_shade=FULL_SHADE):
    """The weak-border join in plain numpy, on the region graph, iterated to its fixed point.

    A region may join a seed when its mean chromaticity is within ``chroma_lim`` of the seed's, or,
    for a seed below ``shade_from``, when its chromaticity less the shift of that much more sun or
    shade (``t v``, ``t`` = its change in log brightness / ``v[2]``, ``|t| <= full_shade``) is."""
    k = road.size
    lab = labels.ravel()
    means = _region_means(labels, img, k)
    chroma = means[:, :2]
    top = np.full(k, labels.shape[0])
    np.minimum.at(top, lab, np.repeat(np.arange(labels.shape[0]), labels.shape[1]))
    ok = np.zeros(k, bool)
    for j in range(mus.shape[0]):
        inv = np.linalg.inv(covs[j, :2, :2])
        d = chroma - mus[j, :2]
        ok |= np.einsum("ij,jk,ik->i", d, inv, d) <= chroma_lim**2
        lift = means[:, 2] - mus[j, 2]
        if mus[j, 2] < shade_from:
            t = lift / SHADE_DIRECTION[2]
            d = d - t[:, None] * SHADE_DIRECTION[None, :2]
            ok |= (lift != 0) & (np.abs(t) <= full_shade) & (np.einsum("ij,jk,ik->i", d, inv, d) <= chroma_lim**2)
    ok &= (top >= top_min) & ~road & (weak > 0)   # weak 0 = off (a border of zero magnitude is not weak)
    g = grad.astype(np.float64)
    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    gs = np.concatenate([(0.5 * (g[:, :-1] + g[:, 1:])).ravel(), (0.5 * (g[:-1, :] + g[1:, :])).ravel()])
    vert = np.concatenate([np.zeros(labels[:, :-1].size), np.ones(labels[:-1, :].size)])
    diff = a != b
    lo, hi = np.minimum(a, b)[diff].astype(np.int64), np.maximum(a, b)[diff].astype(np.int64)
    codes, inv = np.unique(lo * k + hi, return_inverse=True)
    cnt = np.bincount(inv)
    gmed = np.median(g[np.isin(labels, np.flatnonzero(start))]) if start.any() else 0.0
    is_weak = (np.bincount(inv, weights=gs[diff]) <= weak * (gmed if gmed > 0 else 1.0) * cnt) & \
              (np.bincount(inv, weights=vert[diff]) >= across * cnt)
    pa, pb = codes // k, codes % k
    inc = start.copy()
    while True:
        step = np.zeros(k, bool)
        for x, y in ((pa, pb), (pb, pa)):
            m = inc[x] & ~inc[y] & (road[y] | (ok[y] & is_weak))
            step[y[m]] = True
        if not step.any():
            return inc, inc & ok
        inc |= step


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), h=st.integers(2, 48), w=st.integers(2, 48), n_colours=st.integers(2, 40),
       block=st.integers(1, 8), weak=st.sampled_from([0.0, 0.5, 1.0, 4.0]), across=st.sampled_from([0.0, 0.6, 1.0]),
       connected=st.booleans(), one_hue=st.booleans(), along_shade=st.booleans())
# draws where the join adds 22, 16 and 6 regions; then two where the shade-line test adds 1 of 1 and 18 of 28
@example(seed=2591, h=40, w=10, n_colours=11, block=2, weak=4.0, across=1.0, connected=True, one_hue=True,
         along_shade=False)
@example(seed=7720, h=22, w=20, n_colours=12, block=1, weak=1.0, across=1.0, connected=True, one_hue=True,
         along_shade=False)
@example(seed=3430, h=39, w=11, n_colours=17, block=2, weak=0.5, across=0.6, connected=True, one_hue=True,
         along_shade=False)
@example(seed=3, h=40, w=13, n_colours=5, block=1, weak=1.0, across=0.6, connected=True, one_hue=True, along_shade=True)
@example(seed=6, h=26, w=30, n_colours=8, block=2, weak=4.0, across=0.0, connected=True, one_hue=True, along_shade=True)
def test_candidate_kernel_equals_the_numpy_iteration(seed, h, w, n_colours, block, weak, across, connected, one_hue,
                                                     along_shade):
    """The region-graph search (open-addressing border table, CSR graph, one search) against the
    join done the slow way: border strengths from ``np.unique``, rounds until nothing changes.
    Labels that are not 4-connected regions (``connected`` False) have more pairs than a planar
    graph and exercise the table's fallback size.  With ``one_hue`` the regions differ in
    brightness only, so most pass the chromaticity test and the join runs in about a quarter of
    the draws (random palettes almost never pass it: a review found the join in 2 of 300 such
    draws); the explicit examples join.  With ``along_shade`` as well the regions are one surface
    under more or less shade (features moved along SHADE_DIRECTION) and the seeds are below
    ``shade_from``, so the join's shade-line test is the one that decides."""
    rng = np.random.default_rng(seed)
    if connected or one_hue:   # scattered labels almost never pass the top-row test: one hue, regions
        labels, k = _region_labels(rng, h, w, min(n_colours, 12), block)
    else:
        k = min(n_colours, h * w)
        labels = rng.integers(0, k, (h, w)).astype(np.int32)
        labels.flat[:k] = np.arange(k)
    shade_from = 4.0
    if one_hue and along_shade:
        # one surface, each region under its own amount of shade t (t < 0: sunnier), seeds shaded
        base = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.5, 0.2), rng.uniform(3.0, 3.8)])
        feats = base[None, :] + rng.uniform(-1.2, 0.3, (k, 1)) * SHADE_DIRECTION[None, :3]
        g = 3.0 * np.exp(feats[:, 2]) / (np.exp(feats[:, 0]) + 1.0 + np.exp(feats[:, 1]))
        palette = np.clip(np.rint(np.stack([g * np.exp(feats[:, 0]), g, g * np.exp(feats[:, 1])], 1)
                                  - FEATURE_OFFSET), 0, 255)
        shade_from = 4.2
    elif one_hue:
        # one chromaticity (the features' channels are c + FEATURE_OFFSET), brightness free
        base = rng.integers(40, 200, 3)[None, :] + FEATURE_OFFSET
        palette = np.rint(base * rng.uniform(0.6, 1.25, (k, 1)) - FEATURE_OFFSET)
    else:
        palette = rng.integers(0, 256, (k, 3))
    img = np.clip(palette[labels] + rng.integers(-6, 7, (h, w, 3)), 0, 255).astype(np.uint8)
    grad = (rng.random((h, w), dtype=np.float32) * 60).astype(np.float32)
    grad[rng.random((h, w)) < 0.3] = 0.0
    road = rng.random(k) < 0.4
    start = np.zeros(k, bool)
    start[rng.integers(0, k, 2)] = True
    road |= start
    slot = np.full(k, -1, np.int32)
    slot[np.flatnonzero(start)] = np.arange(start.sum())
    _i, mus, covs, chroma, gmed = road_share_kernel(labels, img, grad, slot, k, *feature_tables(FEATURE_OFFSET),
                                                    0.02**2, chi2_quantile(0.9, 4), SHADE_DIRECTION, 0.04,
                                                    shade_from)
    top_min = 0.4 * h
    inc, added = candidate_kernel(labels, grad, start, road, k, chroma, gmed, mus, covs, weak, 2.0, top_min, across,
                                  SHADE_DIRECTION, shade_from, FULL_SHADE)
    want_inc, want_added = _weak_join_reference(labels, img, grad, start, road, mus, covs, weak, 2.0, top_min, across,
                                                shade_from)
    np.testing.assert_array_equal(inc, want_inc)
    np.testing.assert_array_equal(added, want_added)
    assert not (added & road).any()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), h=st.integers(4, 60), w=st.integers(4, 60), n_colours=st.integers(2, 10),
       block=st.integers(1, 6), share=st.floats(0.0, 1.0))
def test_candidate_regions_without_the_join_are_connected_to_seeds(seed, h, w, n_colours, block, share):
    """With ``weak`` 0 the region-graph search is :func:`connected_to_seeds` (cv2's components) on
    SRM-like labels: the same candidate, pixel for pixel, with seeds chosen as the pipeline chooses them."""
    rng = np.random.default_rng(seed)
    labels, k = _region_labels(rng, h, w, n_colours, block)
    seeds, _grounded = _seeds_grounded(labels, k, 0.1)
    is_seed = np.zeros(k, bool)
    is_seed[seeds] = True
    road = (rng.random(k) < share) | is_seed
    params = RoadParams(weak=0.0)
    stats = (np.zeros((k, 3)), 0.0)
    cand, joined = candidate_regions(road, is_seed, labels, np.zeros((h, w), np.float32), stats,
                                     np.zeros((0, 4)), np.zeros((0, 4, 4)), params)
    np.testing.assert_array_equal(cand, connected_to_seeds(road, labels, is_seed, params))
    assert not joined.any()
    horizon = dataclasses.replace(params, horizon=0.5)
    cand, _ = candidate_regions(road, is_seed, labels, np.zeros((h, w), np.float32), stats,
                                np.zeros((0, 4)), np.zeros((0, 4, 4)), horizon)
    np.testing.assert_array_equal(cand, connected_to_seeds(road, labels, is_seed, horizon))


def test_the_weak_join_under_a_horizon_stays_below_it():
    rgb, _ = make_scene("structured_road", seed=2)
    joined = []
    for params in (RoadParams(horizon=0.5), RoadParams(horizon=0.5, weak=50.0)):
        small, seg, _frame = working_frame(rgb, params)
        cand, info = classify(small, seg, params)
        assert not cand[: int(0.5 * cand.shape[0])].any()
        assert cand.any()
        assert not (info["weak_joined"] & (info["road_share"] >= params.frac)).any()
        assert np.isin(np.flatnonzero(info["weak_joined"]), info["labels"][cand > 0]).all()
        joined.append(int(info["weak_joined"].sum()))
    assert joined[0] < joined[1]  # the rounds under a horizon do join


def test_a_region_joined_above_the_horizon_only_is_not_reported_joined():
    """A region that borders the candidate only above the horizon is cut with the rows: ``joined``
    (what the carried model keeps) does not name it (found by a review)."""
    h, w = 12, 6
    labels = np.zeros((h, w), np.int32)
    labels[5] = 1
    labels[6:] = 2
    road = np.array([False, False, True])
    stats = (np.zeros((3, 3)), 0.0)
    mus, covs = np.zeros((1, 4)), np.eye(4)[None] * 0.01
    for horizon, want in ((0.5, [False, False, False]), (0.0, [False, True, False])):
        params = RoadParams(horizon=horizon, weak=4.0)
        cand, joined = candidate_regions(road, road.copy(), labels, np.zeros((h, w), np.float32), stats,
                                         mus, covs, params)
        assert joined.tolist() == want
        assert not cand[: int(horizon * h)].any()


def test_the_weak_join_is_off_at_zero_and_checked():
    assert RoadParams(weak=0.0).check().weak == 0.0
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="weak must be"):
            RoadParams(weak=bad).check()


def test_two_colour_road_analytic():
    """A grey road under a blue sky: the road model finds exactly the road."""
    img = np.zeros((225, 300, 3), np.uint8)
    img[:] = (70, 110, 200)
    img[120:] = (90, 90, 90)
    mask = segment_drivable(img).mask
    assert (mask[121:] == 255).all() and (mask[:119] == 0).all()  # the blurred boundary row is its own region


def test_a_differently_coloured_verge_is_not_road():
    img = np.zeros((225, 300, 3), np.uint8)
    img[:] = (70, 110, 200)
    img[120:, :] = (40, 140, 40)     # grass
    img[120:, 90:210] = (95, 95, 95)  # road strip through the bottom-centre cell
    mask = segment_drivable(img).mask
    assert (mask[130:, 100:200] == 255).all()
    assert (mask[130:, :80] == 0).all() and (mask[130:, 220:] == 0).all()


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(SCENE_KINDS), seed=st.integers(0, 50))
def test_a_wider_ellipsoid_never_shrinks_the_road(kind, seed):
    """Monotone in p: every step after the chi-square test (horizon, connectivity, opening, column fill)
    keeps a superset.  Abstention is off here: it is deliberately not monotone (a wider ellipsoid
    that leaks up to the horizon makes the model trust its seed less and shrink); so is the cut
    along the road's boundaries (a wider candidate holds more of the verge beside an edge line,
    and that edge then has two materials beside it and cuts: Hypothesis found the structured road, seed 1)."""
    rgb, _ = make_scene(kind, seed=seed)
    narrow = segment_drivable(rgb, params=RoadParams(p=0.9, reach=0.0, boundary=0.0)).mask
    wide = segment_drivable(rgb, params=RoadParams(p=0.999, reach=0.0, boundary=0.0)).mask
    assert not np.any((narrow > 0) & (wide == 0))


def _work(rgb):
    return cv2.resize(rgb, WORK_SHAPE[::-1], interpolation=cv2.INTER_AREA)


def test_candidates_are_connected_to_the_seeds_and_below_the_horizon():
    small = _work(make_scene("structured_road", seed=2)[0])
    params = RoadParams(horizon=0.5)
    cand, info = classify(small, srm(small, q=params.q), params)
    h = WORK_SHAPE[0]
    assert cand[: h // 2].sum() == 0 and info["seeds"].size >= 1
    n, comp = cv2.connectedComponents(cand, connectivity=4)
    seg = srm(small, q=params.q)
    seeded = set(np.unique(comp[np.isin(seg.labels, info["seeds"]) & (cand > 0)]))
    assert set(np.unique(comp[cand > 0])) <= seeded


def test_a_vehicle_in_the_upper_cell_is_not_a_seed():
    """Ground contact: a car ahead covering the upper half of the bottom-centre cell is no seed; the road below it is."""
    img = np.zeros((225, 300, 3), np.uint8)
    img[:] = (70, 110, 200)            # sky
    img[110:] = (90, 90, 90)           # grey road, bottom half
    img[150:205, 90:210] = (150, 20, 20)  # a red car ahead: rows 150-205 cover the upper 60 % of the cell (188-225)
    small = _work(img)
    seg = srm(small, q=RoadParams().q)
    seeds = seed_regions(seg.labels, seg.n_regions, 0.1)
    car = seg.labels[int(170 / 2), 75]
    road = seg.labels[-1, 75]
    assert car not in seeds and road in seeds
    mask = segment_drivable(img).mask
    assert (mask[160:200, 100:200] == 0).all()   # the car is not drivable
    assert (mask[212:, 20:280] == 255).all()      # the road in front of it is


def test_a_verge_reaching_into_the_cell_corner_is_no_seed():
    """Issue 27: a field beside the road that reaches into the bottom-centre cell's corner (20 % of it) is
    no seed, so its colour is not road (the previous code took it as a second seed and painted it)."""
    img = np.zeros((225, 300, 3), np.uint8)
    img[:] = (70, 110, 200)                 # sky
    img[110:] = (40, 120, 40)               # grass
    img[110:, 80:180] = (100, 100, 100)     # grey road, 80 % of the cell's width (columns 100-200)
    img[140:, 180:] = (170, 140, 100)       # a dirt field on the right, into the cell's last 20 columns
    img = np.clip(img + np.random.default_rng(0).normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    res = segment_drivable(img)
    assert RoadParams().lateral > 0
    assert not res.mask[150:, 190:].any()           # the field is red
    assert (res.mask[130:, 90:170] == 255).all()    # the road is green
    old = segment_drivable(img, params=RoadParams(lateral=0.0)).mask
    assert (old[150:, 190:] == 255).all()           # control: as a seed, the field is painted


def test_seeds_without_ground_contact_are_all_the_ground_under_the_robot():
    """Issue 27: when no region covers ``seed_share`` of the cell with ground contact (leaf litter splits
    the ground under the robot into small regions), every region reaching the cell's lower half is a
    seed.  The code before took the largest region of the cell alone (region 1 here: [1]), and on a
    leaf-litter floor that one patch's Gaussian left most of the ground red."""
    labels = np.zeros(WORK_SHAPE, np.int32)
    labels[: WORK_SHAPE[0] - 5] = 1    # region 1 ends 5 rows above the bottom; region 0 holds only the last 5 rows
    labels[:, :40] = 2                 # region 2 lies left of the cell (columns 50-99): never a seed
    seeds = seed_regions(labels, 3, 0.9)  # no region covers 90 % of the cell
    assert seeds.tolist() == [0, 1]
    labels[WORK_SHAPE[0] - 5:, 40:] = 1   # now region 1 reaches the bottom and holds most of the cell
    assert seed_regions(labels, 3, 0.9).tolist() == [1]   # the largest, as before, but now it is ground


def _road_scene(road_rgb, *, road_to_top=False):
    """A 300x225 frame: sky above, verges (green) left and right, a road of ``road_rgb`` in the middle.

    With ``road_to_top`` a wall of the road's colour stands behind it up to the top of the frame
    (the seed's appearance also matches what stands on the ground).
    """
    img = np.zeros((225, 300, 3), np.uint8)
    img[:] = (70, 110, 200)
    img[110:] = (40, 120, 40)
    img[110:, 80:220] = road_rgb
    if road_to_top:
        img[:110, 100:200] = road_rgb
    rng = np.random.default_rng(0)
    return np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)


def test_a_trusted_seed_gives_the_full_model():
    res = segment_drivable(_road_scene((120, 120, 120)))
    assert res.confidence == 1.0 and res.abstained is None
    assert (res.mask[130:, 100:200] == 255).all()


def test_a_seed_that_reaches_the_top_abstains_to_the_ground_ahead():
    """Issue 27 item 1: road-like regions reaching the top of the frame -> shrink below ``cap``, and say so."""
    params = RoadParams()
    res = segment_drivable(_road_scene((120, 120, 120), road_to_top=True), params=params)
    assert res.abstained == "seed reaches the horizon"
    assert 0.0 <= res.confidence < 1.0
    assert not res.mask[: int(params.cap * 225) - 2].any()   # nothing green above the sure rows
    assert (res.mask[130:, 100:200] == 255).all()            # the ground just ahead stays green
    off = segment_drivable(_road_scene((120, 120, 120), road_to_top=True), params=RoadParams(reach=0.0))
    assert off.abstained is None and off.mask[:50, 120:180].all()  # control: without abstention it over-fills


def test_a_dim_seed_abstains_when_asked():
    dark = _road_scene((25, 25, 25))
    assert segment_drivable(dark).abstained is None          # dim = 0 (the shipped choice) never triggers
    res = segment_drivable(dark, params=RoadParams(dim=40.0))
    assert res.abstained == "dim seed" and res.confidence == pytest.approx(25 / 40, abs=0.1)


def test_confidence_falls_as_the_candidate_reaches_higher():
    info = {"seed_grey": 100.0, "grounded": True}
    params = RoadParams(reach=0.4)
    confs = []
    for top in (60, 40, 20, 0):
        cand = np.zeros(WORK_SHAPE, np.uint8)
        cand[top:, 50:100] = 1
        mask, conf, reason = abstain(cand, info, params)
        confs.append(conf)
        if conf < 1:
            assert reason == "seed reaches the horizon" and not mask[: int(params.cap * WORK_SHAPE[0])].any()
        else:
            assert reason is None and (mask == cand).all()
    assert confs[0] == 1.0 and confs == sorted(confs, reverse=True) and confs[-1] == 0.0
    mask, conf, reason = abstain(np.ones(WORK_SHAPE, np.uint8), {**info, "grounded": False}, params)
    assert conf == 0.0 and reason == "seed not ground" and mask[-1].all()


def test_open_ground_is_a_flat_front_under_a_smooth_sky():
    """Issue 27 item 3: a candidate reaching the horizon across the frame, under a sky smoother than
    it, is open ground (not shrunk); a trunk climbing to the top, a narrow front or a textured top
    (a forest's canopy) is not."""
    h, w = WORK_SHAPE
    rng = np.random.default_rng(0)
    grad = np.zeros(WORK_SHAPE, np.float32)
    grad[40:] = rng.uniform(0, 60, (h - 40, w))           # textured ground, smooth sky
    flat = np.zeros(WORK_SHAPE, np.uint8)
    flat[40:] = 1
    flat[30:40, 20:30] = 1                                # a rock's top above the horizon: a spike, not the front
    assert open_ground(flat, 0.7, grad)
    assert not open_ground(flat, 0.0, grad)               # front = 0: the test is off
    canopy = grad.copy()
    canopy[:40] = rng.uniform(0, 120, (40, w))            # the top is more textured than the ground
    assert not open_ground(flat, 0.7, canopy)
    trunk = np.zeros(WORK_SHAPE, np.uint8)
    trunk[60:] = 1
    trunk[0:60, 40:60] = 1                                # climbs to the top edge: no room for a sky
    trunk[0:60, 100:110] = 1
    assert not open_ground(trunk, 0.7, grad)
    narrow = np.zeros(WORK_SHAPE, np.uint8)
    narrow[60:] = 1
    narrow[30:60, 30:120] = 1                             # a front over 0.6 of the width
    assert not open_ground(narrow, 0.7, grad) and open_ground(narrow, 0.5, grad)
    # abstain: the flat front is not shrunk (and says so to the column fill); without the sky it is
    info = {"seed_grey": 100.0, "grounded": True, "grad": grad}
    mask, conf, reason = abstain(flat, info, RoadParams())
    assert reason is None and conf == 1.0 and (mask == flat).all() and info["open_ground"]
    mask, conf, reason = abstain(flat, {**info, "grad": canopy}, RoadParams())
    assert reason == "seed reaches the horizon" and not mask[: int(RoadParams().cap * h)].any()
    # hills above the horizon (a band of their own that ends within it) go; the ground stays
    labels = np.zeros(WORK_SHAPE, np.int32)
    labels[40:] = 1                                       # the ground: the seed
    labels[30:40] = 2                                     # the hills: end 10 rows below the front's top
    labels[60:, :20] = 3                                  # a patch of ground beside the seed
    hills = flat.copy()
    hills[30:40] = 1
    kept = below_the_horizon(hills, {"labels": labels, "sizes": np.bincount(labels.ravel()),
                                     "seeds": np.array([1])})
    assert not kept[:40].any() and kept[40:].all()


def test_no_labelled_frame_is_open_ground(roads_dir, monkeypatch):
    """``front`` is fixed, not cross-validated, because no labelled frame is open ground at the default
    (0.97), measured where the pipeline decides it (on the candidate after the opening); the highest
    front of a frame that reaches above ``reach`` with room for a sky is ``umich_early_forest1``'s 0.84
    (with the horizon cut and the running-on surface too), kept out by the front and by its canopy's
    texture (2026-11-29; ``front`` 0.6 was tried and withdrawn, docs/ACCURACY.md).  Control:
    at 0.3 CamVid 0016E5_02400 (front 0.333) passes."""
    import scmr_mesh.imaging.pipeline as pipeline

    seen: list[bool] = []

    def spy(candidate, info, params):
        out = abstain(candidate, info, params)
        seen.append(bool(info.get("open_ground")))
        return out

    monkeypatch.setattr(pipeline, "abstain", spy)

    def open_frames(front):
        out = []
        for item in load_manifest(roads_dir):
            seen.clear()
            segment_drivable(load_frame(item.image), params=dataclasses.replace(DEFAULT_PARAMS, front=front))
            assert len(seen) == 1
            if seen[0]:
                out.append(item.image.name)
        return out

    assert open_frames(DEFAULT_PARAMS.front) == []
    assert open_frames(0.3) == ["camvid_0016E5_02400.png"]


@pytest.mark.parametrize("share", [0.62, 0.8])
def test_a_road_grey_wall_under_a_clear_sky_is_not_open_ground(share):
    """A hostile review's scene (2026-11-29): a wall of the road's grey with a flat top across ``share`` of
    the width, standing on the grass ahead of a road under a clear sky.  Its top is a flat front under a
    smooth sky; with ``front`` 0.6 it passed as open ground and was painted green (precision 0.59 /
    0.53).  It must abstain and stay red.  (A wall across the whole width still passes: a flat front over
    0.97 of the width under a smooth sky is what open ground is, and one frame cannot tell them apart.)"""
    h, w = WORK_SHAPE[0] * 2 + 1, WORK_SHAPE[1] * 2
    yy, xx = np.mgrid[:h, :w]
    rng = np.random.default_rng(0)

    def tex(a, c):
        g = rng.uniform(-1, 1, (h // c + 2, w // c + 2)).astype(np.float32)
        return a * cv2.resize(g, (g.shape[1] * c, g.shape[0] * c), interpolation=cv2.INTER_CUBIC)[:h, :w, None]

    img = np.stack([150 + 40 * yy / 80, 175 + 30 * yy / 80, 215 + 10 * yy / 80], -1).astype(np.float32)
    grass = yy > 80
    img[grass] = ((90, 130, 70) + tex(12, 4))[grass]
    road = grass & (np.abs(xx - 150) <= 90 * (yy - 80) / (h - 80) + 2)
    img[road] = ((100, 100, 100) + tex(8, 6))[road]
    wall = (yy > 50) & (yy <= 100) & (xx >= w * (1 - share))
    img[wall] = ((80, 80, 80) + tex(8, 6))[wall]
    img = np.clip(img + np.random.default_rng(1).normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    res = segment_drivable(img)
    assert res.abstained == "seed reaches the horizon"
    assert score(res.mask, road & ~wall)["precision"] >= 0.95
    assert not (res.mask.astype(bool) & wall).any()


@pytest.mark.parametrize("bad", [dict(gamma=0), dict(p=1.0), dict(noise=0), dict(horizon=1.0), dict(gap=-1),
                                 dict(reach=1.0), dict(cap=1.0), dict(opening=-1), dict(dim=300),
                                 dict(seed_share=0), dict(frac=0), dict(frac=1.5), dict(q=0), dict(q=float("inf")),
                                 dict(shade=-0.1), dict(sunlit=300), dict(front=1.5)])
def test_bad_params_are_refused(bad):
    with pytest.raises(InputError):
        segment_drivable(np.zeros((225, 300, 3), np.uint8), params=RoadParams(**bad))


def test_best_masks_equal_segment_drivable_for_every_params():
    """best_masks classifies once per params other than AFTER_CLASSIFY (what cross-validation uses):
    each of its masks, confidences and abstentions must still be segment_drivable's for those params."""
    import itertools

    from scmr_mesh.imaging.pipeline import best_masks

    grid = {"p": (0.9, 0.99), "frac": (0.3, 0.5), "opening": (0, 9), "reach": (0.0, 0.35), "cap": (0.4, 0.5),
            "standing": (False, True), "gap": (10, 20)}
    params = [RoadParams(**dict(zip(grid, v))) for v in itertools.product(*grid.values())]
    rgb = make_scene("structured_road", seed=1)[0]  # a frame on which each of these fields changes the mask
    got = list(best_masks(rgb, params))
    for prm, (mask, conf, why) in zip(params, got):
        want = segment_drivable(rgb, params=prm)
        assert (mask == want.mask).all() and (conf, why) == (want.confidence, want.abstained), prm
    for i, f in enumerate(grid):  # so a field wrongly taken as read after classify is caught
        stride = math.prod(len(v) for v in list(grid.values())[i + 1:])
        assert any((got[j][0] != got[j + stride][0]).any() for j in range(len(params))
                   if getattr(params[j], f) == grid[f][0]), f
    # a frame on open ground: abstain marks the shared classification (open_ground), so a cache
    # that did not copy it before abstain gave 32 of these 128 masks another column fill
    rgb = make_scene("desert", seed=2)[0]
    for prm, (mask, conf, why) in zip(params, best_masks(rgb, params)):
        want = segment_drivable(rgb, params=prm)
        assert (mask == want.mask).all() and (conf, why) == (want.confidence, want.abstained), prm


def test_cross_validation_on_the_shared_images(roads_dir):
    """Leave-one-dataset-out: the shipped defaults are what the grid chooses on all images, and floors hold.

    The shared data grew from 17 to 60 labelled pairs in 7 datasets (CamVid with its dusk sequence,
    KITTI road and semantics, ORFD, RELLIS-3D, UMich campus sidewalk and forest floor).  On them the
    grid chooses SRM Q 2048 (the shipped default since), and the floors are the measurement on
    those 60 images: in-sample mean IoU >= 0.78 and cross-validated >= 0.76 (measured 0.783 /
    0.767; on the first 17 images 0.818 / 0.799).  Every dataset beats the trivial bottom-half
    prior but the forest floor (0.702 vs 0.748): the open defect of issue 27, asserted as such so
    the test says when it is fixed.

    Issue 27 (calibrated abstention, a horizontal opening, and the operating point: the best IoU
    among combinations with mean precision >= 0.88 on the training images) raised the measurement
    to 0.797 / 0.777 (0.743 averaged over datasets, was 0.731), precision 0.890 in-sample / 0.878
    cross-validated (was 0.861 / 0.856); the floors follow (0.79 / 0.77 / 0.74, precision 0.88 /
    0.87).  The forest floor rose to 0.730, still below its prior (0.748).

    Issue 27 (lateral seeds: a seed region other than the cell's main one must have its centroid in
    the middle half of the width) raised ORFD's cross-validated precision from 0.829 to 0.856 and
    its IoU from 0.794 to 0.820 (a dirt field beside the track was a second seed), every fold
    choosing it; means 0.798 / 0.779 / 0.747.  The ORFD precision >= 0.85 fails on the code before.

    Issue 27 (a fragmented ground is the seed: when no region of the cell has both the share and
    ground contact, every region reaching the cell's lower half seeds the model, not the largest
    alone) raised the forest floor's cross-validated IoU from 0.730 to 0.757, above its prior
    (0.748), so every dataset now beats the prior; the code before fails that assertion.

    Issue 27 (2026-11-28: every choice among the combinations that keep the synthetic scenes at
    their floors, as the shipped defaults must): CamVid's fold had chosen ``shade`` 0, ``standing``
    False, ``p`` 0.99 and ``frac`` 0.5 (0.804 on CamVid), constants that could not be shipped (four
    of the five synthetic kinds fall below their floors under them); now every fold chooses the
    in-sample constants (only they are left), so the cross-validated means are the in-sample ones,
    0.800 / 0.755 / precision 0.892 (were 0.783 / 0.751 / 0.878), and the floors follow (0.795 /
    0.75 / 0.885).  The code before fails the first and the last.

    Issue 27 (2026-11-28, later: the weak-border join, ``weak`` 0 / 4 / 6 in the grid, all three
    meeting the synthetic floors at ``frac`` 0.3): the folds now choose differently (``weak`` 0, 4
    or 6), so the cross-validation again says something beyond the in-sample figure: 0.804 over
    images (the target, 0.80), 0.757 over datasets, precision 0.887; in-sample 0.815.  The code
    before fails the in-sample floor (0.800) and the fold choices' variety.

    Issue 27 (2026-11-28, evening: the shade term one-sided, shade only darkens): a warm, bright
    verge or pavement no longer passes as the road "in more sun".  The campus sidewalk's fold goes
    0.737 -> 0.803, the mean over datasets 0.757 -> 0.765, over images 0.804 -> 0.806; the
    in-sample choice is now ``weak`` 6.  Precision over images falls 0.887 -> 0.8846 (CamVid's
    IoU loses 0.008, its precision 0.007), so its floor here was lowered from 0.885 to 0.88 (the operating point's own
    floor on the training images).  The code before fails the campus's and the datasets' floors.

    Issue 27 (2026-11-29: the cut along the road's boundaries, ``boundary`` 0 / 0.3 in the grid):
    a straight edge up the frame between two materials (a kerb, a verge's edge line, a wall's
    foot) cuts the candidate.  CamVid 0.828 -> 0.846 (precision 0.883 -> 0.909), KITTI road
    0.618 -> 0.638; over images 0.807 -> 0.829, over datasets 0.765 -> 0.786, precision 0.885 ->
    0.901.  Every fold now chooses the in-sample constants (56 of the 768 combinations meet the
    synthetic floors, so each fold had a choice), so the cross-validated figures equal the
    in-sample ones.  The code before fails CamVid's and the datasets' floors.

    The cut of rough surfaces (``rough``, 2026-11-29) is not in the grid: every fold chose it (0.833
    over images, 0.795 over datasets, KITTI semantics' precision 0.839), also with its blur guard,
    but a strong blur over the bottom centre fools it (tests/test_imaging_rough.py), so the grid
    and the figures here are those before it.
    """
    import json

    res = cross_validate(roads_dir)
    manifest = json.loads((roads_dir / "manifest.json").read_text())
    items = manifest["items"]
    assert set(res["per_dataset"]) >= {"camvid", "kitti_road", "orfd", "rellis3d"}
    assert sum(r["n"] for r in res["per_dataset"].values()) == len(items) >= 60
    chosen = res["in_sample"]["params"]
    assert {k: getattr(DEFAULT_PARAMS, k) for k in chosen} == chosen
    assert res["mean"]["in_sample_iou"] >= 0.825
    assert res["mean"]["cv_iou"] >= 0.825
    assert res["mean_of_datasets"]["cv_iou"] >= 0.78   # 0.765 before the cut along the boundaries
    assert res["per_dataset"]["camvid"]["cv_iou"] >= 0.84   # 0.828 before it
    assert res["per_dataset"]["umich_campus_sidewalk"]["cv_iou"] >= 0.78   # 0.737 with the symmetric shade term
    assert res["per_dataset"]["orfd"]["cv_precision"] >= 0.85
    assert res["mean"]["in_sample_precision"] >= 0.895
    assert res["mean"]["cv_precision"] >= 0.895
    assert res["min_precision"] == 0.88
    # every choice meets the synthetic scenes' floors, the shipped defaults' among them
    syn = res["synthetic"]
    assert syn["checked"] and 2 <= syn["fit"] < res["combinations"]   # the folds choose among several
    choices = [RoadParams(**chosen)] + [RoadParams(**r["cv_params"]) for r in res["per_dataset"].values()]
    assert synthetic_scores(choices)["fits"].all()
    for d, r in res["per_dataset"].items():
        assert r["cv_iou"] > r["bottom_half_iou"], d
    assert res["per_dataset"]["umich_forest_traversable"]["cv_iou"] >= 0.755   # 0.730 before
    table = format_cv_table(res)
    assert "CV IoU" in table and "rellis3d" in table and "prec" in table and "recall" in table
    # the obstacles painted drivable: under the in-sample choice they are what `scmr eval` reports for
    # the shipped defaults (another path: segment_drivable frame by frame), under the folds' choices
    # each dataset's figures are its fold's
    ob = res["obstacles"]
    assert ob["in-sample"] == evaluate(roads_dir, baselines=False)["obstacles"]["best"]
    assert ob["in-sample"]["camvid"]["vehicle"]["green"] > 0 and "kitti_road" not in ob["in-sample"]
    for d, r in res["per_dataset"].items():
        if r["cv_params"] == chosen and d in ob["in-sample"]:
            assert ob["cross-validated"][d] == ob["in-sample"][d], d
    assert "obstacles painted drivable" in table and "cross-validated" in table.split("obstacles painted")[1]


def test_the_operating_point_chooses_among_the_allowed_combinations():
    """:func:`choose_combination`: the best training IoU among the allowed combinations whose training
    precision reaches the floor; the floor is dropped when no allowed combination reaches it, and
    the allowed set when it is empty (then the floor applies to all)."""
    iou = np.array([[0.9, 0.9, 0.1], [0.8, 0.8, 0.1], [0.7, 0.7, 0.9], [0.6, 0.6, 0.9]])
    prec = np.array([[0.8, 0.8, 0.1], [0.9, 0.9, 0.1], [0.95, 0.95, 0.1], [0.99, 0.99, 0.99]])
    train = np.array([True, True, False])   # the third image is the held-out one: never looked at
    assert choose_combination(iou, prec, train, 0.0) == 0
    assert choose_combination(iou, prec, train, 0.88) == 1
    assert choose_combination(iou, prec, train, 0.88, np.array([True, False, True, True])) == 2
    assert choose_combination(iou, prec, train, 0.97, np.array([True, True, True, False])) == 0   # none precise
    assert choose_combination(iou, prec, train, 0.88, np.zeros(4, bool)) == 1   # nothing allowed: all are


def test_a_combination_below_the_synthetic_floors_does_not_fit():
    """:func:`synthetic_scores` on the shipped defaults and on constants that lower the synthetic tunnel
    below its 0.85 (``frac`` 0.5, docs/ACCURACY.md 2026-11-28): the first fits, the second does not."""
    res = synthetic_scores([DEFAULT_PARAMS, RoadParams(frac=0.5)])
    assert res["fits"].tolist() == [True, False]
    assert res["iou"]["tunnel"][1] < synthetic_floor("tunnel") <= res["iou"]["tunnel"][0]


def test_the_synthetic_floors_hold_iou_and_precision_per_kind(monkeypatch):
    """:func:`synthetic_fits`: a kind below its IoU floor, or below the precision floor, fails the params;
    a kind still below the 0.85 target is held to its own floor (none since 2026-11-29, when the desert
    left at 0.910; here the desert's old 0.77 is put back)."""
    import scmr_mesh.imaging.evaluate as evaluate

    assert all(synthetic_floor(k) == 0.85 for k in SCENE_KINDS)
    monkeypatch.setitem(evaluate.SYNTHETIC_KNOWN_BELOW, "desert", 0.77)
    assert synthetic_floor("tunnel") == 0.85 and synthetic_floor("desert") == 0.77
    iou = {"tunnel": np.array([0.86, 0.86, 0.84, 0.86]), "desert": np.array([0.78, 0.78, 0.78, 0.76])}
    prec = {"tunnel": np.array([0.90, 0.84, 0.90, 0.90]), "desert": np.array([0.90, 0.90, 0.90, 0.90])}
    assert synthetic_fits(iou, prec).tolist() == [True, False, False, False]


def test_the_cross_validation_without_the_synthetic_floors_is_the_old_protocol(roads_dir):
    """``synthetic=False`` (``--no-synthetic-floors``): CamVid's fold chooses constants that could not ship
    (``shade`` 0, ``standing`` False, ...: they fail the synthetic floors), CV 0.783 over images; and a
    grid none of whose combinations meets the floors is refused with the flag named, not cross-validated."""
    res = cross_validate(roads_dir, synthetic=False)
    assert res["synthetic"] == {"checked": False}
    assert "not checked" in format_cv_table(res)
    camvid = RoadParams(**res["per_dataset"]["camvid"]["cv_params"])
    assert camvid != DEFAULT_PARAMS and not synthetic_scores([camvid])["fits"][0]
    assert res["mean"]["cv_iou"] < res["mean"]["in_sample_iou"]
    # CamVid's obstacles are those of its fold's choice, not of the in-sample one
    ob = res["obstacles"]
    cv_car, in_car = ob["cross-validated"]["camvid"]["vehicle"], ob["in-sample"]["camvid"]["vehicle"]
    assert cv_car["inner"] == in_car["inner"] and cv_car["green"] < in_car["green"]   # 4,597 and 6,796 px
    with pytest.raises(InputError, match="no-synthetic-floors"):
        cross_validate(roads_dir, grid={"frac": (0.5,)})


def test_the_feature_tables_are_built_once_when_threads_race(monkeypatch):
    """The 16 robots of a `scmr swarm` warm the pipeline at once: each thread that found a lazy
    table cache empty appended the three tables, the kernel got 16 arguments instead of 13
    ("too many arguments: expected 13, got 16") and those robots lost their local fallback.
    The tables are built at import now: nothing is built when threads ask for them."""
    import threading

    from scmr_mesh.imaging import road_model

    def built_late(off):
        raise AssertionError("the feature tables were built at call time, where threads race")

    monkeypatch.setattr(road_model, "feature_tables", built_late)
    got = []
    threads = [threading.Thread(target=lambda: got.append(len(road_model._tables()))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert got == [3] * 8 and len(road_model._TABLES) == 3


def test_the_evaluation_module_examples_hold():
    """The examples in ``scmr_mesh.imaging.evaluate``'s docstrings (the operating point, the floors) run."""
    import doctest

    from scmr_mesh.imaging import evaluate

    failed, tried = doctest.testmod(evaluate)
    assert failed == 0 and tried >= 4


# ---------------------------------------------------------------- open ground's horizon and front
SAND = (200.0, 165.0, 115.0)
HILLS = (160.0, 130.0, 120.0)
SKY = (170.0, 195.0, 225.0)
SHADE_GAIN = (0.62, 0.66, 0.78)   # the synthetic scenes' cast shadow: skylight only


def _open_frame(foot, slope=0.0, above=HILLS, seed=0):
    """A working frame of open ground: sky, then ``above`` from row 30 down to the ground's far edge,
    a line through (75, ``foot``) with ``slope``, then sand; grain and sensor noise."""
    h, w = WORK_SHAPE
    yy, xx = np.mgrid[:h, :w]
    rng = np.random.default_rng(seed)
    edge = foot + slope * (xx - w / 2)
    img = np.empty((h, w, 3), np.float32)
    img[:] = SKY
    img[yy >= 30] = above
    img[yy >= edge] = SAND
    img *= 1 + 0.03 * rng.standard_normal((h, w, 1)).astype(np.float32)
    img += rng.normal(0, 2, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("slope", [0.0, 0.1, -0.15])
def test_the_horizon_is_the_lowest_material_boundary_near_the_candidate_top(slope):
    """Hills of another material stand on the sand's far edge and the candidate took them: the line
    found is the sand's far edge (their foot), not the sky's edge above them, at the camera's roll."""
    small = _open_frame(45, slope)
    cand = np.zeros(WORK_SHAPE, np.uint8)
    cand[30:] = 1
    found = horizon_line(small, cand)
    assert found is not None
    assert abs(found.slope - slope) <= 0.02 and abs(found.row - 45) <= 1.5


def test_a_short_or_steep_edge_is_no_horizon():
    """A shadow's edge across 0.4 of the width, or one at a slope of 0.3 (a cast shadow seen in
    perspective), is no horizon: the line found is the sky's edge at row 30 (control: across the
    whole width and level, the edge at row 45 is taken, whatever lies above it)."""
    shaded = np.array([c * g for c, g in zip(SAND, SHADE_GAIN)])
    cand = np.zeros(WORK_SHAPE, np.uint8)
    cand[30:] = 1
    h, w = WORK_SHAPE
    yy, xx = np.mgrid[:h, :w]
    short = _open_frame(45, above=tuple(shaded))
    short[(yy >= 30) & (yy < 45) & (xx >= 0.4 * w)] = np.array(SAND, np.uint8)
    assert horizon_line(short, cand)[1] == pytest.approx(30, abs=1)
    steep = _open_frame(30, above=SAND)
    steep[(yy >= 30) & (yy < 50 + 0.3 * (xx - w / 2))] = np.rint(shaded).astype(np.uint8)
    assert horizon_line(steep, cand)[1] == pytest.approx(30, abs=1)
    assert horizon_line(_open_frame(45, above=tuple(shaded)), cand)[1] == pytest.approx(45, abs=1)


def test_cut_above_horizon_keeps_the_ground_below_the_line_and_what_touches_a_seed():
    small = _open_frame(45)
    h, w = WORK_SHAPE
    labels = np.zeros(WORK_SHAPE, np.int32)
    labels[45:] = 1                          # the sand, the seed region
    labels[30:45] = 2                        # the hills
    cand = np.zeros(WORK_SHAPE, np.uint8)
    cand[30:] = 1
    cand[5:8, 10:14] = 1                     # a speck in the sky, apart from the seed
    labels[70:73, 100:110] = 3               # a piece below the line, apart from the seed's
    cand[69:74, 99:111] = 0
    cand[70:73, 100:110] = 1
    info = {"small": small, "labels": labels, "sizes": np.bincount(labels.ravel()), "seeds": np.array([1])}
    cut = cut_above_horizon(cand, info, horizon_line(small, cand))
    assert not cut[:44].any() and cut[46:69].all() and not cut[70:73, 100:110].any()
    assert cut[74:].all()


@pytest.mark.parametrize("width", [1, 3, 9, 150])
def test_horizon_line_never_raises_on_noise(width):
    """A reviewer's fuzzing (2026-11-29) found random 112 x 3 frames on which the least-squares fit got no
    votes and raised; any frame and candidate gives a line or None."""
    rng = np.random.default_rng(width)
    for _ in range(300):
        small = rng.integers(0, 256, (WORK_SHAPE[0], width, 3), dtype=np.uint8)
        cand = (rng.uniform(size=(WORK_SHAPE[0], width)) < rng.uniform()).astype(np.uint8)
        found = horizon_line(small, cand)
        assert found is None or (np.isfinite(found.slope) and np.isfinite(found.row))


def _gaussians(mu_chroma, sd=0.03):
    """``classify``-like seed Gaussians: one seed with mean log R/G, log B/G ``mu_chroma`` and log brightness 5."""
    mus = np.array([[*mu_chroma, 5.0, 0.5]])
    covs = np.diag([sd ** 2, sd ** 2, 0.04, 0.04])[None]
    return mus, covs


def test_same_surface_is_the_seeds_hue_in_the_same_light_or_in_shade_never_a_grey_seeds():
    sand = np.log([SAND[0] / SAND[1], SAND[2] / SAND[1]])
    mus, covs = _gaussians(sand)
    v = SHADE_DIRECTION
    chroma = np.array([
        [*sand, 5.0],                                   # the seed's surface
        [*(sand + 0.5 * v[:2]), 5.0 + 0.5 * v[2]],      # the same in half a shadow (darker, bluer)
        [*(sand - 0.5 * v[:2]), 5.0 - 0.5 * v[2]],      # "more sun": brighter and less blue; no
        [0.0, 0.0, 5.0],                                # grey concrete
        [*(sand + [0.0, 0.4]), 5.0],                    # another hue
    ])
    got = same_surface({"chroma": chroma, "mus": mus, "covs": covs})
    assert got.tolist() == [True, True, False, False, False]
    grey_mus, grey_covs = _gaussians((0.01, -0.02))
    assert not same_surface({"chroma": np.array([[0.01, -0.02, 5.0]]), "mus": grey_mus, "covs": grey_covs}).any()


def _front_case(beside, beside_top=40):
    """A sand candidate under a sky (rows 40 down) whose right 20 columns stop at row 80: above them, from
    row ``beside_top`` to row 80, lies a region of chromaticity ``beside`` (log R/G, log B/G, log
    brightness), painted in the frame as sand moved along the shade direction (the region's
    statistics in ``info`` are ``beside`` as given)."""
    h, w = WORK_SHAPE
    sand = np.log([SAND[0] / SAND[1], SAND[2] / SAND[1]])
    mus, covs = _gaussians(sand)
    labels = np.zeros(WORK_SHAPE, np.int32)            # 0: sky
    labels[40:, :] = 1                                 # 1: the seed's sand
    labels[beside_top:80, w - 20:] = 2                 # 2: the region beside
    cand = (labels == 1).astype(np.uint8)
    small = _open_frame(40, above=SKY)
    small[labels == 2] = np.rint(np.array(SAND) * np.array(SHADE_GAIN)).astype(np.uint8)
    chroma = np.array([[0.0, 0.0, 5.0], [*sand, 5.0], beside])
    info = {"labels": labels, "sizes": np.bincount(labels.ravel()), "seeds": np.array([1]), "chroma": chroma,
            "mus": mus, "covs": covs, "small": small}
    return cand, info


def test_the_front_counts_the_seeds_surface_running_on_to_the_horizon():
    """The lens's dark corner: the same sand, darker and bluer (shade's move), was not taken, but runs on
    to the horizon band below the horizon line; its columns count for the front.  Grass there does
    not, nor a region of the sand's surface that stands far above the front's row (a wall, not
    ground), nor anything when no horizon line was found (the frame without ``small``)."""
    v = SHADE_DIRECTION
    sand = np.log([SAND[0] / SAND[1], SAND[2] / SAND[1]])
    shaded = [*(sand + 0.3 * v[:2]), 5.0 + 0.3 * v[2]]
    cand, info = _front_case(shaded)
    assert front_share(cand) == pytest.approx(130 / 150)
    assert front_share(cand, info) == 1.0
    assert info["horizon"] is not None and info["horizon"].row == pytest.approx(40, abs=1)
    no_line = {n: v for n, v in info.items() if n not in ("small", "horizon")}
    assert front_share(cand, no_line) == pytest.approx(130 / 150)
    cand, info = _front_case([-0.3, -0.5, 4.8])        # green grass
    assert front_share(cand, info) == pytest.approx(130 / 150)
    cand, info = _front_case(shaded, beside_top=5)     # the same surface, but its top far above the front
    assert front_share(cand, info) == pytest.approx(130 / 150)


def _ground_with_a_wall(ground, wall_cols, wall_rows, upper=None, hz=70, seed=0):
    """A 225 x 300 frame (a reviewer's construction, 2026-11-29): sky, open textured ground of colour
    ``ground`` from row ``hz``, and a textured wall of 0.92 of the ground's colour over the pixel
    columns ``wall_cols`` and rows ``wall_rows``, with ``upper`` the gains of its part above the
    horizon's row (in shade: darker and bluer); returns the frame, the truth and the wall."""
    h, w = FRAME_SHAPE
    yy, xx = np.mgrid[:h, :w]
    rng = np.random.default_rng(seed)

    def tex(a, c):
        g = rng.uniform(-1, 1, (h // c + 2, w // c + 2)).astype(np.float32)
        return a * cv2.resize(g, (g.shape[1] * c, g.shape[0] * c), interpolation=cv2.INTER_CUBIC)[:h, :w, None]

    img = np.minimum(np.stack([140 + 60 * yy / hz, 170 + 45 * yy / hz, 210 + 15 * yy / hz], -1), 235).astype(np.float32)
    g = yy >= hz
    img[g] = (np.array(ground, np.float32) * (0.88 + 0.2 * (yy[..., None] - hz) / (h - hz)) + tex(10, 5))[g]
    wall = (yy >= wall_rows[0]) & (yy < wall_rows[1]) & (xx >= wall_cols[0]) & (xx < wall_cols[1])
    colour = 0.92 * np.array(ground, np.float32)
    img[wall] = (colour + tex(6, 4))[wall]
    if upper is not None:
        top = wall & (yy < hz)
        img[top] = (colour * np.array(upper, np.float32) + tex(6, 4))[top]
    img = np.clip(img + np.random.default_rng(seed + 1).normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    return img, g & ~wall, wall


SAND_WALL = (195, 165, 120)
DIRT = (150, 120, 85)


@pytest.mark.parametrize("ground,cols,rows,upper", [
    (SAND_WALL, (0, 105), (40, 140), None),
    (SAND_WALL, (150, 195), (45, 120), None),
    (DIRT, (180, 300), (35, 130), None),
    (SAND_WALL, (0, 105), (30, 140), tuple(np.array(SHADE_GAIN) ** 0.3)),
    (DIRT, (0, 105), (30, 140), tuple(np.array(SHADE_GAIN) ** 0.6)),
    (SAND_WALL, (150, 170), (30, 150), None),
])
def test_a_wall_of_the_grounds_colour_on_open_ground_stays_red(ground, cols, rows, upper):
    """Two hostile reviews' scenes (2026-11-29): a wall of nearly the ground's colour standing on open
    ground, its top above the horizon (with ``upper``, its part above the horizon's row in shade, so a
    colour step lies on the horizon line across it; the last one 20 px wide).  A front measured on the
    candidate cut at the horizon line passed them (the first three before a "standing column" rule,
    the last three with it: precision down to 0.59, the wall's lower part green).  The front is
    measured on the candidate as it is, so the wall's top is no front, and the frame abstains with
    the wall red above ``cap``."""
    img, truth, wall = _ground_with_a_wall(ground, cols, rows, upper)
    res = segment_drivable(img)
    assert res.abstained == "seed reaches the horizon"
    # the abstention keeps the rows below ``cap`` (the ground just ahead; a wall merged with the
    # ground there is the per-frame model's old limit), never the wall above them
    cap_row = int(DEFAULT_PARAMS.cap * FRAME_SHAPE[0])
    assert not (res.mask.astype(bool) & wall)[:cap_row].any()


@pytest.mark.parametrize("seed", [0, 2, 7])
def test_distant_hills_above_the_desert_horizon_stay_red(seed):
    """The synthetic desert's hills (seeds 0, 2, 7: precision 0.86 / 0.90 / 0.89 before the horizon cut,
    2026-11-29): SRM merges them with the far sand, so regions straddle the horizon; the cut takes them out."""
    img, truth = make_scene("desert", seed=seed)
    res = segment_drivable(img)
    assert res.abstained is None
    assert score(res.mask, truth)["precision"] >= 0.94


def test_desert_sand_in_shade_at_the_horizon_keeps_the_front():
    """Seed 6 of the synthetic desert: a shadow band near the horizon and the lens's dark corner keep
    columns of the candidate short, so the front fell under 0.97 and the mask was shrunk to ``cap``
    (IoU 0.55).  The same sand runs on there to the horizon, so it is open ground now.  (Seeds 1 and
    5 still abstain: hills joined above the horizon set the front's row, and measuring the front on
    the candidate cut at the horizon, which passed them, let walls through.)"""
    img, truth = make_scene("desert", seed=6)
    res = segment_drivable(img)
    assert res.abstained is None and res.confidence == 1.0
    s = score(res.mask, truth)
    assert s["iou"] >= 0.78 and s["precision"] >= 0.9
