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


@njit(cache=True, nogil=True)
def b2_table(n, q):
    """``b2(R)`` of Nock & Nielsen for every region size 0..n of an n-pixel image (entry 0 unused)."""
    g = 256.0
    log_inv_delta = math.log(6.0) + 2.0 * math.log(float(n))  # ln(1/delta), delta = 1/(6 |I|^2)
    out = np.empty(n + 1, np.float64)
    out[0] = 0.0
    for s in range(1, n + 1):
        out[s] = _b2(s, q, g, log_inv_delta)
    return out


# Per-region record, 16 bytes: [sum R, sum G, sum B, size] as int32 (exact: at most
# 255 * |I|).  Means are computed when tested (sum / size in float64, as before) and
# b2 comes from a per-size table, so the working set (record + parent, 20 bytes a
# pixel) is a third of the former 64-byte float64 record: 1.35 MB at 300x225.
_SIZE = 3


@njit(cache=True, nogil=True)
def _union(parent, acc, a, b):
    # attach the smaller region to the larger; on a tie the larger index to the smaller
    if acc[a, _SIZE] < acc[b, _SIZE] or (acc[a, _SIZE] == acc[b, _SIZE] and a > b):
        a, b = b, a
    parent[b] = a
    for c in range(4):
        acc[a, c] += acc[b, c]


@njit(cache=True, nogil=True)
def srm_kernel(img, q, min_size, b2t):
    """Statistical region merging of an (H, W, 3) uint8 C-contiguous image.

    ``b2t`` is :func:`b2_table` of ``H * W`` pixels and ``q``.
    Returns (labels (H, W) int32, means (n, 3) float64, sizes (n,) int64).
    """
    h, w = img.shape[0], img.shape[1]
    n = h * w
    flat = img.reshape(n, 3)

    # 4-connected pairs in a fixed order: raster order of the first pixel p,
    # its right neighbour (code 2p) before its down neighbour (code 2p + 1).
    npairs = h * (w - 1) + (h - 1) * w
    key = np.empty(2 * n, np.uint8)
    start = np.zeros(257, np.int64)
    for y in range(h):
        for x in range(w):
            p = y * w + x
            r0 = np.int32(flat[p, 0])
            g0 = np.int32(flat[p, 1])
            b0 = np.int32(flat[p, 2])
            if x + 1 < w:
                f = max(abs(r0 - np.int32(flat[p + 1, 0])), abs(g0 - np.int32(flat[p + 1, 1])),
                        abs(b0 - np.int32(flat[p + 1, 2])))
                key[2 * p] = f
                start[f + 1] += 1
            if y + 1 < h:
                f = max(abs(r0 - np.int32(flat[p + w, 0])), abs(g0 - np.int32(flat[p + w, 1])),
                        abs(b0 - np.int32(flat[p + w, 2])))
                key[2 * p + 1] = f
                start[f + 1] += 1
    # stable counting sort by f = max channel difference (0..255)
    for v in range(256):
        start[v + 1] += start[v]
    order = np.empty(npairs, np.int32)
    for y in range(h):
        for x in range(w):
            p = y * w + x
            if x + 1 < w:
                v = key[2 * p]
                order[start[v]] = 2 * p
                start[v] += 1
            if y + 1 < h:
                v = key[2 * p + 1]
                order[start[v]] = 2 * p + 1
                start[v] += 1

    parent = np.empty(n, np.int32)
    acc = np.empty((n, 4), np.int32)
    for p in range(n):
        parent[p] = p
        for c in range(3):
            acc[p, c] = flat[p, c]
        acc[p, _SIZE] = 1

    for j in range(npairs):
        code = order[j]
        p = code >> 1
        a = _find(parent, p)
        b = _find(parent, p + 1 if (code & 1) == 0 else p + w)
        if a == b:
            continue
        na = acc[a, _SIZE]
        nb = acc[b, _SIZE]
        bound = math.sqrt(b2t[na] + b2t[nb])
        fa = float(na)
        fb = float(nb)
        if (
            abs(acc[a, 0] / fa - acc[b, 0] / fb) <= bound
            and abs(acc[a, 1] / fa - acc[b, 1] / fb) <= bound
            and abs(acc[a, 2] / fa - acc[b, 2] / fb) <= bound
        ):
            _union(parent, acc, a, b)

    # small-region rule: a second pass over the same pair order merges any
    # region smaller than min_size pixels into its neighbour.  A pair whose two
    # pixels both lie in regions of at least min_size pixels when the pass
    # starts can never merge (regions only grow), so only pairs touching a
    # pixel of a small region are looked at.
    if min_size > 1:
        small = np.empty(n, np.uint8)
        for p in range(n):  # flatten every path so the finds below are one step
            r = _find(parent, p)
            parent[p] = r
            small[p] = 1 if acc[r, _SIZE] < min_size else 0
        for j in range(npairs):
            code = order[j]
            p = code >> 1
            o = p + 1 if (code & 1) == 0 else p + w
            if small[p] | small[o]:
                a = _find(parent, p)
                b = _find(parent, o)
                if a != b and (acc[a, _SIZE] < min_size or acc[b, _SIZE] < min_size):
                    _union(parent, acc, a, b)

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
            size = float(acc[p, _SIZE])
            for c in range(3):
                out_means[lab, c] = acc[p, c] / size
            out_sizes[lab] = acc[p, _SIZE]
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


@njit(cache=True, nogil=True)
def _inv4(m):
    # Gauss-Jordan with partial pivoting on a 4x4 matrix (symmetric positive definite here)
    a = m.copy()
    inv = np.eye(4)
    for c in range(4):
        piv = c
        for r in range(c + 1, 4):
            if abs(a[r, c]) > abs(a[piv, c]):
                piv = r
        if piv != c:
            for j in range(4):
                t = a[c, j]
                a[c, j] = a[piv, j]
                a[piv, j] = t
                t = inv[c, j]
                inv[c, j] = inv[piv, j]
                inv[piv, j] = t
        d = a[c, c]
        for j in range(4):
            a[c, j] /= d
            inv[c, j] /= d
        for r in range(4):
            if r != c:
                f = a[r, c]
                if f != 0.0:
                    for j in range(4):
                        a[r, j] -= f * a[c, j]
                        inv[r, j] -= f * inv[c, j]
    return inv


@njit(cache=True, nogil=True)
def road_share_kernel(labels, img, grad, slot, k, lut, lsum, tex, noise2, limit, shade_dir, shade2, shade_from):
    """The road model of a frame in two passes over its pixels.

    Pixel features (tables from ``road_model.feature_tables``): ``log(fR/fG)``, ``log(fB/fG)``,
    ``log((fR+fG+fB)/3)`` with f = channel + offset, and ``log1p(round(grad)/8)`` (grad
    clipped to 0..2047).  Pass 1 gathers the pixel moments of every seed region
    (``slot[r] >= 0``): seed ``j`` is the Gaussian with the mean and the unbiased
    covariance of its pixels plus ``noise2 * I`` plus ``shade2 * v v^T`` (``v`` = ``shade_dir``,
    the direction in which shade moves a surface's features) for a seed whose mean log
    brightness is at least ``shade_from`` (a sunlit seed).  Pass 2 counts, per region, the pixels
    inside some seed's ellipsoid ``(x - mu)^T C^-1 (x - mu) <= limit`` (pixels of a seed
    region are not tested; the caller takes seeds as road).  The shade term is one-sided: a
    pixel on the sunny side of a sunlit seed is tested against the covariance ``C0`` without it,
    since shade only darkens (issue 27: a warm, bright verge beside a sunlit road passed as the
    road "in more sun").  The side is the sign of ``v^T C0^-1 (x - mu)``, the pixel's most likely
    amount of shade given the seed's own spread (negative: sunnier than the seed); on that
    boundary both tests give the same distance, so the rule is continuous.  The distance without
    the term is the one with it plus ``shade2 (v^T C0^-1 d)^2 / (1 + shade2 v^T C0^-1 v)``
    (Sherman-Morrison), so the sunny side costs a multiply, not a second quadratic form.

    Returns ``inside`` (k,) int64, ``mus`` (s, 4) and ``covs`` (s, 4, 4) float64, and for the
    weak-border join (:func:`candidate_kernel`) ``chroma`` (k, 3) float64, each region's mean
    ``log(fR/fG)``, ``log(fB/fG)`` and log brightness (computed only when there is a seed), and ``gmed``, the
    median Sobel magnitude of the seed pixels (0 when there are none).
    """
    h, w = labels.shape
    s = 0
    for r in range(k):
        if slot[r] + 1 > s:
            s = slot[r] + 1
    # each pixel's features are made once, in the pass that needs them (a seed pixel's in pass 1,
    # any other's in pass 2): no (h * w, 4) array to write and read back
    f = np.empty(4, np.float64)
    chroma = np.zeros((k, 3), np.float64)
    npx = np.zeros(k, np.float64)
    gvals = np.empty(h * w, np.float64)
    nseed = 0
    m1 = np.zeros((s, 4), np.float64)
    m2 = np.zeros((s, 4, 4), np.float64)
    ns = np.zeros(s, np.float64)
    for y in range(h):
        for x in range(w):
            j = slot[labels[y, x]]
            if j >= 0:
                _pixel_features(img, grad, y, x, lut, lsum, tex, f)
                ns[j] += 1.0
                r = labels[y, x]
                chroma[r, 0] += f[0]
                chroma[r, 1] += f[1]
                chroma[r, 2] += f[2]
                npx[r] += 1.0
                gvals[nseed] = grad[y, x]
                nseed += 1
                for a in range(4):
                    fa = f[a]
                    m1[j, a] += fa
                    for b in range(a, 4):
                        m2[j, a, b] += fa * f[b]
    mus = np.zeros((s, 4), np.float64)
    covs = np.zeros((s, 4, 4), np.float64)
    icovs = np.zeros((s, 4, 4), np.float64)
    sunny = np.zeros(s, np.bool_)
    wv = np.zeros((s, 4), np.float64)      # C0^-1 v, C0 the covariance without the shade term
    gain = np.zeros(s, np.float64)         # shade2 / (1 + shade2 v^T C0^-1 v)
    for j in range(s):
        n = ns[j]
        if n > 0:
            for a in range(4):
                mus[j, a] = m1[j, a] / n
        for a in range(4):
            for b in range(a, 4):
                c = (m2[j, a, b] - n * mus[j, a] * mus[j, b]) / (n - 1.0) if n > 4 else 0.0
                covs[j, a, b] = c
                covs[j, b, a] = c
        for a in range(4):
            covs[j, a, a] += noise2
        if mus[j, 2] >= shade_from:
            sunny[j] = True
            plain = _inv4(covs[j])
            vw = 0.0
            for a in range(4):
                for b in range(4):
                    wv[j, a] += plain[a, b] * shade_dir[b]
                vw += shade_dir[a] * wv[j, a]
            gain[j] = shade2 / (1.0 + shade2 * vw)
            for a in range(4):
                for b in range(4):
                    covs[j, a, b] += shade2 * shade_dir[a] * shade_dir[b]
        icovs[j] = _inv4(covs[j])
    inside = np.zeros(k, np.int64)
    d = np.empty(4, np.float64)
    for y in range(h):
        for x in range(w):
            r = labels[y, x]
            if slot[r] < 0 and s > 0:
                _pixel_features(img, grad, y, x, lut, lsum, tex, f)
                chroma[r, 0] += f[0]
                chroma[r, 1] += f[1]
                chroma[r, 2] += f[2]
                npx[r] += 1.0
                for j in range(s):
                    along = 0.0
                    for a in range(4):
                        d[a] = f[a] - mus[j, a]
                        along += d[a] * wv[j, a]
                    q = 0.0
                    for a in range(4):
                        t = 0.0
                        for b in range(4):
                            t += icovs[j, a, b] * d[b]
                        q += d[a] * t
                    if sunny[j] and along < 0.0:
                        # shade only darkens: on the sunny side the distance without the shade
                        # term, q0 = q + gain * along^2 (Sherman-Morrison)
                        q += gain[j] * along * along
                    if q <= limit:
                        inside[r] += 1
                        break
    for r in range(k):
        if npx[r] > 0:
            chroma[r, 0] /= npx[r]
            chroma[r, 1] /= npx[r]
            chroma[r, 2] /= npx[r]
    gmed = np.median(gvals[:nseed]) if nseed > 0 else 0.0
    return inside, mus, covs, chroma, gmed


@njit(cache=True, nogil=True)
def _border_table(labels, grad, k, size, top):
    """Per pair of 4-adjacent regions (key ``lo * k + hi``, open addressing, -1 = empty): the sum
    over their neighbouring pixel pairs of the two pixels' mean ``grad``, their number and how
    many are vertical neighbours.  ``full`` is True (and the table incomplete) when more than
    three quarters of the ``size`` slots would be used.  Fills ``top`` (k,), each region's top
    row, on the way (for :func:`candidate_kernel`)."""
    h, w = labels.shape
    mask = size - 1
    keys = np.full(size, -1, np.int64)
    gsum = np.zeros(size, np.float64)
    cnt = np.zeros(size, np.int64)
    vcnt = np.zeros(size, np.int64)
    used = 0
    for y in range(h):
        for x in range(w):
            r = labels[y, x]
            if top[r] > y:
                top[r] = y
            g = np.float64(grad[y, x])
            for dy in range(2):
                yy = y + dy
                xx = x + 1 - dy
                if yy >= h or xx >= w:
                    continue
                o = labels[yy, xx]
                if o == r:
                    continue
                code = np.int64(min(r, o)) * k + max(r, o)
                t = ((code * 2654435761) >> 7) & mask
                while keys[t] != -1 and keys[t] != code:
                    t = (t + 1) & mask
                if keys[t] == -1:
                    used += 1
                    if 4 * used > 3 * size:
                        return keys, gsum, cnt, vcnt, True
                    keys[t] = code
                gsum[t] += 0.5 * (g + np.float64(grad[yy, xx]))
                cnt[t] += 1
                vcnt[t] += dy
    return keys, gsum, cnt, vcnt, False


@njit(cache=True, nogil=True)
def candidate_kernel(labels, grad, start, road, k, chroma, gmed, mus, covs, weak, chroma_lim, top_min, across,
                     shade_dir, shade_from, full_shade):
    """The road model's candidate regions: a search over the region graph from ``start``.

    Returns ``(inc, added)``, (k,) bool each.  From the ``start`` regions, the search takes every
    ``road`` region it reaches over any border (4-adjacent regions, :func:`_border_table`): the
    road-like regions 4-connected to the start, what ``connected_to_seeds`` finds with
    ``cv2.connectedComponents``.  With ``weak`` > 0 it also takes every region that may join
    (``ok``) reached over a weak border, and that region passes the search on: ``added`` names them.
    A region may join when it is not ``road``, its mean chromaticity ``chroma`` lies within
    ``chroma_lim`` (Mahalanobis, the chromatic 2x2 block of ``covs``) of some seed's ``mus`` and its
    top row is at least ``top_min`` (``chroma`` and ``gmed`` come from :func:`road_share_kernel`).
    For a seed without the shade term (``mus[j, 2] < shade_from``: in shade, or a dark surface in
    the sun), the chromaticity tested may also be the region's less ``t * shade_dir[:2]``,
    ``t = lift / shade_dir[2]`` with ``lift`` the region's mean log brightness less the seed's:
    the seed's surface under that much more sun (``t`` < 0) or shade (``t`` > 0), for
    ``|t| <= full_shade`` (one full shadow).
    A border is weak when its mean pixel-pair magnitude is at most ``weak`` x ``gmed`` (1 when
    ``gmed`` is 0) and at least ``across`` of its pixel pairs are vertical neighbours (it runs
    across the frame).  ``inc`` is every region the search took, ``start`` included.
    """
    h, w = labels.shape
    size = 64
    # a partition of the grid into 4-connected regions has a planar adjacency graph (a minor of
    # the grid): at most 3k - 6 pairs, so the table stays under half full; other labels fall back
    while size < 6 * k + 16:
        size *= 2
    top = np.full(k, h, np.int64)
    keys, gsum, cnt, vcnt, full = _border_table(labels, grad, k, size, top)
    if full:
        size = 64
        while size < 4 * h * w + 16:
            size *= 2
        keys, gsum, cnt, vcnt, full = _border_table(labels, grad, k, size, top)
    s = mus.shape[0]
    ok = np.zeros(k, np.bool_)
    lim2 = chroma_lim * chroma_lim
    if weak > 0.0:
        for r in range(k):
            if top[r] >= top_min and not road[r]:
                for j in range(s):
                    c00 = covs[j, 0, 0]
                    c01 = covs[j, 0, 1]
                    c11 = covs[j, 1, 1]
                    det = c00 * c11 - c01 * c01
                    if not det > 0.0:
                        continue
                    dr = chroma[r, 0] - mus[j, 0]
                    db = chroma[r, 1] - mus[j, 1]
                    if (c11 * dr * dr - 2.0 * c01 * dr * db + c00 * db * db) / det <= lim2:
                        ok[r] = True
                        break
                    lift = chroma[r, 2] - mus[j, 2]
                    if mus[j, 2] < shade_from and lift != 0.0 and shade_dir[2] < 0.0:
                        # a seed without the shade term: is the region its surface under more
                        # sun (amount < 0 along v) or more shade (> 0)?  Its chromaticity less
                        # the shift that amount brings
                        amount = lift / shade_dir[2]
                        if abs(amount) > full_shade:
                            continue
                        dr -= amount * shade_dir[0]
                        db -= amount * shade_dir[1]
                        if (c11 * dr * dr - 2.0 * c01 * dr * db + c00 * db * db) / det <= lim2:
                            ok[r] = True
                            break
    limit = weak * (gmed if gmed > 0.0 else 1.0)
    # the region graph as CSR: every pair in both directions, flagged weak or not
    deg = np.zeros(k + 1, np.int64)
    for t in range(size):
        c = keys[t]
        if c >= 0:
            deg[c // k + 1] += 1
            deg[c % k + 1] += 1
    for r in range(k):
        deg[r + 1] += deg[r]
    nbr = np.empty(deg[k], np.int64)
    wk = np.empty(deg[k], np.bool_)
    fill = deg[:k].copy()
    for t in range(size):
        c = keys[t]
        if c >= 0:
            a = c // k
            b = c % k
            weak_t = gsum[t] <= limit * cnt[t] and vcnt[t] >= across * cnt[t]
            nbr[fill[a]] = b
            wk[fill[a]] = weak_t
            fill[a] += 1
            nbr[fill[b]] = a
            wk[fill[b]] = weak_t
            fill[b] += 1
    inc = np.zeros(k, np.bool_)
    stack = np.empty(k, np.int64)
    top_s = 0
    for r in range(k):
        if start[r]:
            inc[r] = True
            stack[top_s] = r
            top_s += 1
    added = np.zeros(k, np.bool_)
    while top_s > 0:
        top_s -= 1
        r = stack[top_s]
        for e in range(deg[r], deg[r + 1]):
            o = nbr[e]
            if not inc[o] and (road[o] or (ok[o] and wk[e])):
                inc[o] = True
                added[o] = ok[o] and not road[o]
                stack[top_s] = o
                top_s += 1
    return inc, added


@njit(cache=True, nogil=True, inline="always")
def _pixel_features(img, grad, y, x, lut, lsum, tex, f):
    """The road model's four features of pixel (y, x) into ``f`` (see :func:`road_share_kernel`)."""
    cr = img[y, x, 0]
    cg = img[y, x, 1]
    cb = img[y, x, 2]
    f[0] = lut[cr] - lut[cg]
    f[1] = lut[cb] - lut[cg]
    f[2] = lsum[np.int32(cr) + np.int32(cg) + np.int32(cb)]
    gv = grad[y, x]
    gi = 2047 if not gv < 2047.0 else (0 if not gv > 0.0 else np.int32(gv + 0.5))
    f[3] = tex[gi]


# OpenCV's INTER_AREA downscale in two passes over whole rows (contiguous, so they vectorize);
# codec.area_resize transposes between them.  Each axis's weights are a CSR table (ptr, idx, w;
# float32, codec._area_table): output line d is sum of w[j] * line idx[j], j in ptr[d]:ptr[d+1],
# summed in OpenCV's order (across first, then down), float32, rounded half to even and clamped.
@njit(cache=True, nogil=True)
def area_rows_kernel(src, ptr, idx, w, out):
    """``out[d] = sum_j w[j] * src[idx[j]]`` for uint8 rows, into float32 ``out``."""
    n_out, length = out.shape
    for d in range(n_out):
        o = out[d]
        j0 = ptr[d]
        r = src[idx[j0]]
        a = w[j0]
        for i in range(length):
            o[i] = np.float32(0.0) + np.float32(r[i]) * a
        for j in range(j0 + 1, ptr[d + 1]):
            r = src[idx[j]]
            a = w[j]
            for i in range(length):
                o[i] += np.float32(r[i]) * a
    return out


@njit(cache=True, nogil=True)
def area_round_kernel(src, ptr, idx, w, out):
    """``out[d] = round(sum_j w[j] * src[idx[j]])`` for float32 rows, into uint8 ``out`` (clamped)."""
    n_out, length = out.shape
    acc = np.empty(length, np.float32)
    for d in range(n_out):
        for j in range(ptr[d], ptr[d + 1]):
            _down_term(acc, w[j], src[idx[j]], j == ptr[d])
        _round_row(acc, out[d])
    return out


@njit(cache=True, nogil=True, inline="always")
def _down_term(acc, a, r, first):
    """One term of a down-sum, in OpenCV's order: ``acc = a * r`` (the first) or ``acc += a * r``."""
    if first:
        for i in range(acc.size):
            acc[i] = a * r[i]
    else:
        for i in range(acc.size):
            acc[i] += a * r[i]


@njit(cache=True, nogil=True, inline="always")
def _round_row(acc, o):
    """``o = uint8(clamp(rint(acc), 0, 255))``: OpenCV's saturating round half to even."""
    for i in range(acc.size):
        v = np.rint(acc[i])
        o[i] = np.uint8(min(max(v, np.float32(0.0)), np.float32(255.0)))


# An exact 2:1 across (best's 300x225 -> 150x112) in one pass: OpenCV's two across terms are
# halves of 8-bit values, so their float32 sum is exact (half the pair's integer sum); each source
# row's sums are made in a row buffer where a down-sum needs them, so no whole-image scratch array
# leaves the cache between frames.  ``src`` is (h, 2 * width * 3) uint8 RGB rows, ``out``
# (height, width * 3); down, the weights and order of ``area_round_kernel``.
@njit(cache=True, nogil=True)
def area_half_kernel(src, ptr, idx, w, out):
    """OpenCV's ``INTER_AREA`` for an exact 2:1 across and a fractional down, same bytes."""
    n_out, length = out.shape
    width = length // 3
    acc = np.empty(length, np.float32)
    buf = np.empty(length, np.float32)
    half = np.float32(0.5)
    for d in range(n_out):
        for j in range(ptr[d], ptr[d + 1]):
            r = src[idx[j]]
            for x in range(width):
                s = 6 * x
                buf[3 * x] = np.float32(np.int32(r[s]) + np.int32(r[s + 3])) * half
                buf[3 * x + 1] = np.float32(np.int32(r[s + 1]) + np.int32(r[s + 4])) * half
                buf[3 * x + 2] = np.float32(np.int32(r[s + 2]) + np.int32(r[s + 5])) * half
            _down_term(acc, w[j], buf, j == ptr[d])
        _round_row(acc, out[d])
    return out


@njit(cache=True, nogil=True)
def boundary_sides_kernel(lines, candidate, small, sides, offset):
    """Per straight edge ``x1, y1, x2, y2`` of ``lines`` (n, 4) int64: what :func:`boundary_lines` tests.

    The edge's pixels are ``rint`` of ``n = max(|dx|, |dy|) + 1`` points evenly spaced from one
    end to the other (numpy's ``linspace``).  Returns (n, 9) float64: the share of those pixels
    with a candidate pixel in their 5x5 neighbourhood (column 0); then for each side (the unit
    normal ``(-(y2 - y1), x2 - x1) / norm``, then its opposite; columns 1-4 and 5-8) the count of
    candidate pixels at the distances ``sides`` (float64) along it and their mean ``log R/G``,
    ``log B/G`` and log brightness (``log(v + offset)``, brightness ``log((R + G + B) / 3 +
    offset)``); columns 9-11 and 12-14 the two sides' mean R, G, B.  A side with no pixels has
    means 0.  Returns (n, 15) float64 (zeros for a line of one pixel).
    """
    n_lines = lines.shape[0]
    h, w = candidate.shape
    out = np.zeros((n_lines, 15), np.float64)
    for li in range(n_lines):
        x1 = lines[li, 0]
        y1 = lines[li, 1]
        x2 = lines[li, 2]
        y2 = lines[li, 3]
        n = max(abs(x2 - x1), abs(y2 - y1)) + 1
        if n < 2:
            continue
        stepx = (x2 - x1) / (n - 1)
        stepy = (y2 - y1) / (n - 1)
        px = np.empty(n, np.int64)
        py = np.empty(n, np.int64)
        inside = 0
        for i in range(n):
            if i == n - 1:
                px[i] = x2
                py[i] = y2
            else:
                px[i] = int(np.rint(i * stepx + x1))
                py[i] = int(np.rint(i * stepy + y1))
            hit = False
            for yy in range(max(py[i] - 2, 0), min(py[i] + 3, h)):
                for xx in range(max(px[i] - 2, 0), min(px[i] + 3, w)):
                    if candidate[yy, xx] != 0:
                        hit = True
                        break
                if hit:
                    break
            if hit:
                inside += 1
        out[li, 0] = inside / n
        nx = -(y2 - y1)
        ny = x2 - x1
        norm = math.sqrt(float(nx * nx + ny * ny))
        fx = nx / norm
        fy = ny / norm
        for k in range(2):
            sign = 1.0 if k == 0 else -1.0
            cnt = 0
            s_rg = 0.0
            s_bg = 0.0
            s_l = 0.0
            s_r = 0.0
            s_g = 0.0
            s_b = 0.0
            for di in range(sides.size):
                d = sides[di]
                for i in range(n):
                    qx = int(np.rint(px[i] + sign * d * fx))
                    qy = int(np.rint(py[i] + sign * d * fy))
                    if qx < 0 or qx >= w or qy < 0 or qy >= h or candidate[qy, qx] == 0:
                        continue
                    r = float(small[qy, qx, 0])
                    g = float(small[qy, qx, 1])
                    b = float(small[qy, qx, 2])
                    lg = math.log(g + offset)
                    s_rg += math.log(r + offset) - lg
                    s_bg += math.log(b + offset) - lg
                    s_l += math.log((r + g + b) / 3.0 + offset)
                    s_r += r
                    s_g += g
                    s_b += b
                    cnt += 1
            c = 1 + 4 * k
            out[li, c] = cnt
            if cnt:
                out[li, c + 1] = s_rg / cnt
                out[li, c + 2] = s_bg / cnt
                out[li, c + 3] = s_l / cnt
                out[li, 9 + 3 * k] = s_r / cnt
                out[li, 10 + 3 * k] = s_g / cnt
                out[li, 11 + 3 * k] = s_b / cnt
    return out


@njit(cache=True, nogil=True)
def _far_side(x1, y1, x2, y2, x, y, s0_pos):
    # pixel (x, y) on the line through (x1, y1)-(x2, y2), or on the side whose cross product's
    # sign is not the robot's (s0_pos)
    cr = (x2 - x1) * (y - y1) - (y2 - y1) * (x - x1)
    return cr == 0 or (cr > 0) != s0_pos


@njit(cache=True, nogil=True)
def boundary_cut_kernel(candidate, lines, max_cut):
    """Cut ``candidate`` (uint8) along each of ``lines`` (n, 4) int64 in turn: the pixels on the far
    side of the line through it (or on it) from the bottom-centre pixel ``(w / 2, h - 1)`` go,
    unless that is none or more than ``max_cut`` of the candidate's pixels.  Returns the cut
    candidate and (n,) uint8: 1 where the line cut."""
    h, w = candidate.shape
    out = candidate.copy()
    total = 0
    for y in range(h):
        for x in range(w):
            if candidate[y, x] != 0:
                total += 1
    used = np.zeros(lines.shape[0], np.uint8)
    sx = w / 2.0
    sy = h - 1.0
    for li in range(lines.shape[0]):
        x1 = lines[li, 0]
        y1 = lines[li, 1]
        x2 = lines[li, 2]
        y2 = lines[li, 3]
        s0 = (x2 - x1) * (sy - y1) - (y2 - y1) * (sx - x1)
        if s0 == 0:
            continue
        s0_pos = s0 > 0
        n_far = 0
        for y in range(h):
            for x in range(w):
                if out[y, x] != 0 and _far_side(x1, y1, x2, y2, x, y, s0_pos):
                    n_far += 1
        if n_far == 0 or n_far > max_cut * total:
            continue
        for y in range(h):
            for x in range(w):
                if out[y, x] != 0 and _far_side(x1, y1, x2, y2, x, y, s0_pos):
                    out[y, x] = 0
        used[li] = 1
    return out, used


@njit(cache=True, nogil=True)
def _row_median(values, mask, y, hist, min_count):
    """The median of ``values[y]`` over ``mask[y] != 0`` (NaN below ``min_count`` pixels), ``hist``
    a 256-bin scratch array."""
    w = values.shape[1]
    for v in range(256):
        hist[v] = 0
    n = 0
    for x in range(w):
        if mask[y, x] != 0:
            hist[values[y, x]] += 1
            n += 1
    if n < min_count or n == 0:
        return np.nan
    k_lo = (n - 1) // 2
    k_hi = n // 2
    lo = -1
    cum = 0
    for v in range(256):
        cum += hist[v]
        if lo < 0 and cum > k_lo:
            lo = v
        if cum > k_hi:
            return (lo + v) / 2.0
    return np.nan


@njit(cache=True, nogil=True)
def row_medians_kernel(values, mask, min_count):
    """Per row of ``values`` (uint8, 2-D), the median over the pixels where ``mask`` (uint8, same
    shape) is not 0: np.median's value (the mean of the two middle values when the count is even),
    from the row's 256-bin histogram; NaN for a row with fewer than ``min_count`` such pixels.
    Returns (rows,) float32."""
    h = values.shape[0]
    out = np.empty(h, np.float32)
    hist = np.zeros(256, np.int64)
    for y in range(h):
        out[y] = np.float32(_row_median(values, mask, y, hist, min_count))
    return out


@njit(cache=True, nogil=True)
def rough_rows_kernel(texture, mask, ratio, min_count):
    """The rough pixels of :func:`~scmr_mesh.imaging.road_model.rough_surface`: per row of
    ``texture`` (uint8, 2-D) with at least ``min_count`` pixels of ``mask`` (uint8), those of
    ``mask`` whose texture exceeds ``ratio`` x the row's median over ``mask`` (at least 1).
    Returns the (rows, cols) uint8 0/1 mask and its count."""
    h, w = texture.shape
    out = np.zeros((h, w), np.uint8)
    hist = np.zeros(256, np.int64)
    total = 0
    for y in range(h):
        med = _row_median(texture, mask, y, hist, min_count)
        if med != med:   # NaN: too few pixels to judge the row
            continue
        limit = ratio * max(med, 1.0)
        ty = texture[y]
        my = mask[y]
        oy = out[y]
        for x in range(w):
            if my[x] != 0 and ty[x] > limit:
                oy[x] = 1
                total += 1
    return out, total
