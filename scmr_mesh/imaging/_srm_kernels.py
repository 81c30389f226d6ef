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
    # path halving: every visited node skips to its grandparent (one pass)
    while parent[i] != i:
        gp = parent[parent[i]]
        parent[i] = gp
        i = gp
    return i


@njit(cache=True, nogil=True)
def _b2(size, q, g, log_inv_delta):
    s = float(size)
    return g * g / (2.0 * q * s) * (min(s, g) * math.log(s + 1.0) + log_inv_delta)


# Per-region record, one 64-byte cache line per region:
# [mean R, mean G, mean B, b2, size, sum R, sum G, sum B]
_MEAN, _B2, _SIZE, _SUM = 0, 3, 4, 5


@njit(cache=True, nogil=True)
def _union(parent, reg, a, b, q, g, log_inv_delta):
    # attach the smaller region to the larger; on a tie the larger index to the smaller
    if reg[a, _SIZE] < reg[b, _SIZE] or (reg[a, _SIZE] == reg[b, _SIZE] and a > b):
        a, b = b, a
    parent[b] = a
    size = reg[a, _SIZE] + reg[b, _SIZE]
    reg[a, _SIZE] = size
    for c in range(3):
        s = reg[a, _SUM + c] + reg[b, _SUM + c]
        reg[a, _SUM + c] = s
        reg[a, _MEAN + c] = s / size
    reg[a, _B2] = _b2(size, q, g, log_inv_delta)


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

    # 4-connected pairs in a fixed order: raster order of the first pixel p,
    # its right neighbour (code 2p) before its down neighbour (code 2p + 1).
    npairs = h * (w - 1) + (h - 1) * w
    key = np.empty(2 * n, np.uint8)
    start = np.zeros(257, np.int64)
    for p in range(n):
        if (p % w) + 1 < w:
            f = 0
            for c in range(3):
                d = abs(np.int32(flat[p, c]) - np.int32(flat[p + 1, c]))
                if d > f:
                    f = d
            key[2 * p] = f
            start[f + 1] += 1
        if p + w < n:
            f = 0
            for c in range(3):
                d = abs(np.int32(flat[p, c]) - np.int32(flat[p + w, c]))
                if d > f:
                    f = d
            key[2 * p + 1] = f
            start[f + 1] += 1
    # stable counting sort by f = max channel difference (0..255)
    for v in range(256):
        start[v + 1] += start[v]
    order = np.empty(npairs, np.int32)
    for p in range(n):
        if (p % w) + 1 < w:
            v = key[2 * p]
            order[start[v]] = 2 * p
            start[v] += 1
        if p + w < n:
            v = key[2 * p + 1]
            order[start[v]] = 2 * p + 1
            start[v] += 1

    parent = np.empty(n, np.int32)
    reg = np.empty((n, 8), np.float64)
    b2_one = _b2(1, q, g, log_inv_delta)
    for p in range(n):
        parent[p] = p
        for c in range(3):
            v = float(flat[p, c])
            reg[p, _MEAN + c] = v
            reg[p, _SUM + c] = v
        reg[p, _B2] = b2_one
        reg[p, _SIZE] = 1.0

    for j in range(npairs):
        code = order[j]
        p = code >> 1
        a = _find(parent, p)
        b = _find(parent, p + 1 if (code & 1) == 0 else p + w)
        if a == b:
            continue
        bound = math.sqrt(reg[a, _B2] + reg[b, _B2])
        if (
            abs(reg[a, 0] - reg[b, 0]) <= bound
            and abs(reg[a, 1] - reg[b, 1]) <= bound
            and abs(reg[a, 2] - reg[b, 2]) <= bound
        ):
            _union(parent, reg, a, b, q, g, log_inv_delta)

    # small-region rule: a second pass over the same pair order merges any
    # region smaller than min_size pixels into its neighbour
    if min_size > 1:
        for p in range(n):  # flatten every path so the finds below are one step
            parent[p] = _find(parent, p)
        for j in range(npairs):
            code = order[j]
            p = code >> 1
            a = _find(parent, p)
            b = _find(parent, p + 1 if (code & 1) == 0 else p + w)
            if a != b and (reg[a, _SIZE] < min_size or reg[b, _SIZE] < min_size):
                _union(parent, reg, a, b, q, g, log_inv_delta)

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
        if parent[p] == p:
            lab = lab_of_root[p]
            for c in range(3):
                out_means[lab, c] = reg[p, _MEAN + c]
            out_sizes[lab] = np.int64(reg[p, _SIZE])
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


@njit(cache=True, nogil=True)
def column_fill_kernel(candidate, max_gap):
    """Column-wise, bottom-up: drivable from the bottom up to the highest candidate
    pixel reached before a run of more than ``max_gap`` non-candidate pixels."""
    h, w = candidate.shape
    out = np.zeros((h, w), np.uint8)
    for x in range(w):
        top = h
        miss = 0
        for y in range(h - 1, -1, -1):
            if candidate[y, x] != 0:
                top = y
                miss = 0
            else:
                miss += 1
                if miss > max_gap:
                    break
        for y in range(top, h):
            out[y, x] = 255
    return out
