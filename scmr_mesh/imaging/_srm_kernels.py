"""numba kernels behind :mod:`scmr_mesh.imaging.srm` and the pipeline (private).

The public functions (with the input checks and the docstrings) live in
``srm.py`` and ``pipeline.py``; these kernels assume valid, C-contiguous input.
All kernels use ``cache=True`` so a new worker process loads the compiled code
from ``__pycache__`` instead of compiling again.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True, nogil=True)
def _b2(size, q, g, log_inv_delta):
    s = float(size)
    return g * g / (2.0 * q * s) * (min(s, g) * math.log(s + 1.0) + log_inv_delta)


@njit(cache=True, nogil=True)
def _union(parent, size, sums, means, b2, a, b, q, g, log_inv_delta):
    # attach the smaller region to the larger; on a tie the larger index to the smaller
    if size[a] < size[b] or (size[a] == size[b] and a > b):
        a, b = b, a
    parent[b] = a
    size[a] += size[b]
    for c in range(3):
        sums[a, c] += sums[b, c]
        means[a, c] = sums[a, c] / size[a]
    b2[a] = _b2(size[a], q, g, log_inv_delta)


@njit(cache=True, nogil=True)
def srm_kernel(img, q, min_size):
    """Statistical region merging of an (H, W, 3) uint8 C-contiguous image.

    Returns (labels (H, W) int32, means (n, 3) float64, sizes (n,) int64).
    """
    h, w = img.shape[0], img.shape[1]
    n = h * w
    flat = img.reshape(n, 3)
    g = 256.0
    log_inv_delta = math.log(6.0) + 2.0 * math.log(float(n))  # ln(1/delta), delta = 1/(6 |I|^2)

    # 4-connected pairs in a fixed order: raster order of the first pixel,
    # its right neighbour before its down neighbour.
    npairs = h * (w - 1) + (h - 1) * w
    pa = np.empty(npairs, np.int32)
    pb = np.empty(npairs, np.int32)
    key = np.empty(npairs, np.int32)
    k = 0
    for y in range(h):
        for x in range(w):
            p = y * w + x
            if x + 1 < w:
                f = 0
                for c in range(3):
                    d = abs(np.int32(flat[p, c]) - np.int32(flat[p + 1, c]))
                    if d > f:
                        f = d
                pa[k] = p
                pb[k] = p + 1
                key[k] = f
                k += 1
            if y + 1 < h:
                f = 0
                for c in range(3):
                    d = abs(np.int32(flat[p, c]) - np.int32(flat[p + w, c]))
                    if d > f:
                        f = d
                pa[k] = p
                pb[k] = p + w
                key[k] = f
                k += 1

    # stable counting sort by f = max channel difference (0..255)
    start = np.zeros(257, np.int64)
    for i in range(npairs):
        start[key[i] + 1] += 1
    for v in range(256):
        start[v + 1] += start[v]
    order = np.empty(npairs, np.int32)
    for i in range(npairs):
        v = key[i]
        order[start[v]] = i
        start[v] += 1

    parent = np.arange(n).astype(np.int32)
    size = np.ones(n, np.int64)
    sums = np.empty((n, 3), np.float64)
    means = np.empty((n, 3), np.float64)
    for p in range(n):
        for c in range(3):
            sums[p, c] = flat[p, c]
            means[p, c] = flat[p, c]
    b2 = np.empty(n, np.float64)
    b2_one = _b2(1, q, g, log_inv_delta)
    for p in range(n):
        b2[p] = b2_one

    for j in range(npairs):
        i = order[j]
        a = _find(parent, pa[i])
        b = _find(parent, pb[i])
        if a == b:
            continue
        bound = math.sqrt(b2[a] + b2[b])
        ok = True
        for c in range(3):
            if abs(means[a, c] - means[b, c]) > bound:
                ok = False
                break
        if ok:
            _union(parent, size, sums, means, b2, a, b, q, g, log_inv_delta)

    # small-region rule: a second pass over the same pair order merges any
    # region smaller than min_size pixels into its neighbour
    if min_size > 1:
        for j in range(npairs):
            i = order[j]
            a = _find(parent, pa[i])
            b = _find(parent, pb[i])
            if a != b and (size[a] < min_size or size[b] < min_size):
                _union(parent, size, sums, means, b2, a, b, q, g, log_inv_delta)

    # labels 0..n_regions-1 in raster order of each region's first pixel
    lab_of_root = np.full(n, -1, np.int32)
    labels = np.empty(n, np.int32)
    count = 0
    for p in range(n):
        r = _find(parent, p)
        if lab_of_root[r] < 0:
            lab_of_root[r] = count
            count += 1
        labels[p] = lab_of_root[r]
    out_means = np.empty((count, 3), np.float64)
    out_sizes = np.empty(count, np.int64)
    for p in range(n):
        r = parent[p]
        if r == p:
            lab = lab_of_root[r]
            for c in range(3):
                out_means[lab, c] = means[r, c]
            out_sizes[lab] = size[r]
    return labels.reshape(h, w), out_means, out_sizes


@njit(cache=True, nogil=True)
def remove_sparse_kernel(drivable, edges, edge_threshold):
    """Column-wise, bottom-up: keep pixels until the first non-drivable pixel or strong edge."""
    h, w = drivable.shape
    out = np.zeros((h, w), np.uint8)
    for x in range(w):
        for y in range(h - 1, -1, -1):
            if drivable[y, x] == 0 or edges[y, x] >= edge_threshold:
                break
            out[y, x] = 255
    return out
