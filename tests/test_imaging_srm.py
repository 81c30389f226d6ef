"""SRM: analytic cases, determinism, and the numba kernel against a slow pure-Python reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.errors import InputError
from scmr_mesh.imaging import srm


def reference_srm(img: np.ndarray, q: float, min_size: int):
    """Nock & Nielsen SRM written plainly from SPEC 1 step 3 (slow; small images only).

    Pairs: raster order, right before down; Python's stable sort by f = max channel
    difference; merge when every channel |mean - mean'| <= sqrt(b2 + b2');
    then merge regions smaller than ``min_size`` along the same pair order.
    """
    h, w, _ = img.shape
    n = h * w
    px = img.reshape(n, 3).astype(np.int64)
    g = 256.0
    log_inv_delta = math.log(6.0) + 2.0 * math.log(float(n))

    def b2(size):
        s = float(size)
        return g * g / (2.0 * q * s) * (min(s, g) * math.log(s + 1.0) + log_inv_delta)

    pairs = []
    for y in range(h):
        for x in range(w):
            p = y * w + x
            if x + 1 < w:
                pairs.append((int(np.abs(px[p] - px[p + 1]).max()), p, p + 1))
            if y + 1 < h:
                pairs.append((int(np.abs(px[p] - px[p + w]).max()), p, p + w))
    pairs.sort(key=lambda t: t[0])  # stable

    parent = list(range(n))
    size = [1] * n
    sums = [[float(v) for v in px[p]] for p in range(n)]

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    def union(a, b):
        parent[b] = a
        size[a] += size[b]
        sums[a] = [sums[a][c] + sums[b][c] for c in range(3)]

    for _, p, r in pairs:
        a, b = find(p), find(r)
        if a == b:
            continue
        bound = math.sqrt(b2(size[a]) + b2(size[b]))
        if all(abs(sums[a][c] / size[a] - sums[b][c] / size[b]) <= bound for c in range(3)):
            union(a, b)
    if min_size > 1:
        for _, p, r in pairs:
            a, b = find(p), find(r)
            if a != b and (size[a] < min_size or size[b] < min_size):
                union(a, b)
    labels = np.empty(n, np.int64)
    first = {}
    for p in range(n):
        root = find(p)
        labels[p] = first.setdefault(root, len(first))
    means = np.zeros((len(first), 3))
    for root, lab in first.items():
        means[lab] = [s / size[root] for s in sums[root]]
    return labels.reshape(h, w), means


def test_two_colour_image_gives_two_regions():
    img = np.zeros((30, 40, 3), np.uint8)
    img[:, :] = (30, 60, 90)
    img[:, 17:] = (200, 180, 20)
    rng = np.random.default_rng(0)
    noisy = np.clip(img.astype(int) + rng.integers(-3, 4, img.shape), 0, 255).astype(np.uint8)
    res = srm(noisy, q=32)
    assert res.n_regions == 2
    assert res.labels.dtype == np.int32 and res.means.dtype == np.float64
    assert np.all(res.labels[:, :17] == 0) and np.all(res.labels[:, 17:] == 1)
    np.testing.assert_allclose(res.means[0], noisy[:, :17].reshape(-1, 3).mean(0))
    np.testing.assert_allclose(res.means[1], noisy[:, 17:].reshape(-1, 3).mean(0))
    assert res.sizes.tolist() == [30 * 17, 30 * 23]
    assert res.image().shape == noisy.shape


def test_srm_is_deterministic():
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    a, b = srm(img, q=64), srm(img.copy(), q=64)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.means, b.means)


def test_larger_q_never_gives_fewer_regions_on_a_gradient():
    img = np.repeat(np.linspace(0, 255, 90).astype(np.uint8)[None, :, None], 30, 0).repeat(3, 2)
    counts = [srm(img, q=q, min_size=0).n_regions for q in (2, 32, 512)]
    assert counts == sorted(counts) and counts[-1] > counts[0]


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 12),
    st.integers(1, 14),
    st.integers(0, 2**32 - 1),
    st.sampled_from([1, 4, 32, 256]),
    st.sampled_from([0, 3, 10]),
    st.sampled_from([2, 8, 256]),
)
def test_numba_kernel_equals_pure_python_reference(h, w, seed, q, min_size, levels):
    rng = np.random.default_rng(seed)
    # few distinct levels give many tied keys, which is where port differences show
    img = (rng.integers(0, levels, (h, w, 3)) * (255 // max(levels - 1, 1))).astype(np.uint8)
    ref_labels, ref_means = reference_srm(img, float(q), min_size)
    res = srm(img, q=q, min_size=min_size)
    np.testing.assert_array_equal(res.labels, ref_labels)
    np.testing.assert_array_equal(res.means, ref_means)
    assert res.sizes.sum() == h * w


def test_small_region_rule_default_and_off():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    off = srm(img, q=32, min_size=0)
    on = srm(img, q=32)  # default min_size = max(1, int(0.001 * 2000)) = 2
    assert on.sizes.min() >= 2 and on.n_regions <= off.n_regions
    assert srm(img, q=32, min_size=100).sizes.min() >= 100


@pytest.mark.parametrize("bad", [0, -1, float("nan"), "x"])
def test_bad_q_is_a_clear_error(bad):
    with pytest.raises(InputError, match="q must be"):
        srm(np.zeros((3, 3, 3), np.uint8), q=bad)
