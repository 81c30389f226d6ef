"""The report's PNG figures, drawn with OpenCV (no plotting library in the project).

:class:`Chart` is a small x/y chart (points, lines, vertical marks, legend, optional log
axes); :func:`image_grid` lays out the four rows of thesis Figures 4.15 and 4.19 (original,
SRM, Otsu, red/green) with one column per image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK = (0, 0, 0)
GREY = (150, 150, 150)
#: BGR colours: our measurements blue/orange, the thesis red.
BLUE, ORANGE, GREEN, PURPLE, RED, TEAL, BROWN = ((200, 110, 30), (20, 140, 245), (40, 160, 40), (160, 60, 160),
                                                  (40, 40, 210), (160, 160, 0), (40, 90, 140))
PALETTE = (BLUE, ORANGE, GREEN, PURPLE, TEAL, BROWN, RED)


def _nice(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        return [lo]
    step = 10 ** math.floor(math.log10((hi - lo) / n))
    for m in (1, 2, 2.5, 5, 10):
        if (hi - lo) / (step * m) <= n:
            step *= m
            break
    start = math.ceil(lo / step) * step
    out, k = [], 0
    while (v := start + k * step) <= hi + 1e-9 * step:  # tick k from an integer, not a float running sum
        out.append(round(v, 10))
        k += 1
    return out


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1e6:
        return f"{v / 1e6:g}M"
    if a >= 1e4:
        return f"{v / 1e3:g}k"
    if a < 0.01:
        return f"{v:.0e}"
    return f"{v:g}" if a >= 1 else f"{v:.2g}"


@dataclass
class Chart:
    """An x/y chart.  Add series, then :meth:`render` to an (H, W, 3) uint8 BGR image."""

    title: str
    xlabel: str
    ylabel: str
    width: int = 620
    height: int = 400
    xlog: bool = False
    ylog: bool = False
    xlim: tuple[float, float] | None = None
    ylim: tuple[float, float] | None = None
    _items: list = field(default_factory=list)
    _legend: list = field(default_factory=list)

    def points(self, xs, ys, colour=BLUE, label: str | None = None, size: int = 3, marker: str = "o") -> "Chart":
        self._items.append(("points", list(map(float, xs)), list(map(float, ys)), colour, size, marker))
        if label:
            self._legend.append((label, colour, "points"))
        return self

    def line(self, xs, ys, colour=BLUE, label: str | None = None, thickness: int = 2, dashed: bool = False) -> "Chart":
        self._items.append(("line", list(map(float, xs)), list(map(float, ys)), colour, thickness, dashed))
        if label:
            self._legend.append((label, colour, "line"))
        return self

    def vline(self, x: float, colour=RED, label: str | None = None, text: str | None = None) -> "Chart":
        self._items.append(("vline", float(x), colour, text))
        if label:
            self._legend.append((label, colour, "line"))
        return self

    def hline(self, y: float, colour=GREY, text: str | None = None) -> "Chart":
        self._items.append(("hline", float(y), colour, text))
        return self

    # ---------------------------------------------------------------- drawing
    def _integer_x(self) -> bool:
        xs = [x for it in self._items if it[0] == "points" for x in it[1] if math.isfinite(x)]
        return bool(xs) and all(float(x).is_integer() for x in xs)

    def _range(self, axis: int) -> tuple[float, float]:
        lim = self.xlim if axis == 0 else self.ylim
        log = self.xlog if axis == 0 else self.ylog
        vals: list[float] = []
        for it in self._items:
            if it[0] in ("points", "line"):
                vals += it[1 + axis]
            elif it[0] == "vline" and axis == 0:
                vals.append(it[1])
            elif it[0] == "hline" and axis == 1:
                vals.append(it[1])
        vals = [v for v in vals if math.isfinite(v) and (v > 0 or not log)]
        if lim is not None:
            return lim
        if not vals:
            return (1.0, 10.0) if log else (0.0, 1.0)
        lo, hi = min(vals), max(vals)
        if log:
            return 10 ** math.floor(math.log10(lo)), 10 ** math.ceil(math.log10(hi) + 1e-9)
        if hi == lo:
            hi = lo + (abs(lo) or 1.0)
        pad = 0.06 * (hi - lo)
        lo = 0.0 if lo >= 0 and lo - pad < 0 + 0.3 * (hi - lo) and axis == 1 else lo - pad
        return lo, hi + pad

    def render(self) -> np.ndarray:
        W, H = self.width, self.height
        ml, mr, mt, mb = 70, 15, 42, 48
        img = np.full((H, W, 3), 255, np.uint8)
        (x0, x1), (y0, y1) = self._range(0), self._range(1)
        lx, ly = self.xlog, self.ylog

        def tx(v: float) -> float:
            return math.log10(v) if lx else v

        def ty(v: float) -> float:
            return math.log10(v) if ly else v

        a0, a1, b0, b1 = tx(x0), tx(x1), ty(y0), ty(y1)

        def px(x: float, y: float) -> tuple[int, int]:
            xx = ml + (tx(x) - a0) / ((a1 - a0) or 1) * (W - ml - mr)
            yy = H - mb - (ty(y) - b0) / ((b1 - b0) or 1) * (H - mt - mb)
            return int(round(xx)), int(round(yy))

        def ok(x: float, y: float) -> bool:
            return math.isfinite(x) and math.isfinite(y) and (x > 0 or not lx) and (y > 0 or not ly)

        cv2.putText(img, self.title, (8, 18), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
        cv2.rectangle(img, (ml, mt), (W - mr, H - mb), BLACK, 1)
        xt = [10 ** k for k in range(int(a0), int(a1) + 1)] if lx else _nice(x0, x1)
        if not lx and self._integer_x():
            xt = [v for v in xt if float(v).is_integer()] or xt
        yt = [10 ** k for k in range(int(b0), int(b1) + 1)] if ly else _nice(y0, y1)
        for v in xt:
            if x0 <= v <= x1:
                p = px(v, y0 if not ly else 10 ** b0)[0]
                cv2.line(img, (p, H - mb), (p, H - mb + 4), BLACK, 1)
                cv2.putText(img, _fmt(v), (p - 12, H - mb + 17), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        for v in yt:
            if y0 <= v <= y1:
                q = px(x0 if not lx else 10 ** a0, v)[1]
                cv2.line(img, (ml - 4, q), (ml, q), BLACK, 1)
                cv2.line(img, (ml + 1, q), (W - mr - 1, q), (235, 235, 235), 1)
                cv2.putText(img, _fmt(v), (4, q + 4), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        cv2.putText(img, self.xlabel, (ml, H - 8), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
        cv2.putText(img, self.ylabel, (8, mt - 8), FONT, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
        clip = img[mt:H - mb + 1, ml:W - mr + 1]
        for it in self._items:
            kind = it[0]
            if kind == "vline" and x0 <= it[1] <= x1 and (it[1] > 0 or not lx):
                p = px(it[1], y0 if not ly else 10 ** b0)[0]
                for yy in range(mt, H - mb, 8):
                    cv2.line(img, (p, yy), (p, min(yy + 4, H - mb)), it[2], 2)
                if it[3]:
                    cv2.putText(img, it[3], (p + 3, mt + 28), FONT, 0.38, it[2], 1, cv2.LINE_AA)
            elif kind == "hline" and y0 <= it[1] <= y1:
                q = px(x0 if not lx else 10 ** a0, it[1])[1]
                cv2.line(img, (ml, q), (W - mr, q), it[2], 1)
                if it[3]:
                    cv2.putText(img, it[3], (ml + 4, q - 3), FONT, 0.36, it[2], 1, cv2.LINE_AA)
            elif kind == "line":
                pts = [px(min(max(x, x0), x1), min(max(y, y0), y1)) for x, y in zip(it[1], it[2]) if ok(x, y)]
                for (pa, pb) in zip(pts, pts[1:]):
                    if it[5]:
                        n = max(1, int(math.hypot(pb[0] - pa[0], pb[1] - pa[1]) // 8))
                        for k in range(0, n, 2):
                            qa = (pa[0] + (pb[0] - pa[0]) * k // n, pa[1] + (pb[1] - pa[1]) * k // n)
                            qb = (pa[0] + (pb[0] - pa[0]) * (k + 1) // n, pa[1] + (pb[1] - pa[1]) * (k + 1) // n)
                            cv2.line(img, qa, qb, it[3], it[4], cv2.LINE_AA)
                    else:
                        cv2.line(img, pa, pb, it[3], it[4], cv2.LINE_AA)
            elif kind == "points":
                for x, y in zip(it[1], it[2]):
                    if ok(x, y) and x0 <= x <= x1 and y0 <= y <= y1:
                        p = px(x, y)
                        if it[5] == "x":
                            cv2.drawMarker(img, p, it[3], cv2.MARKER_TILTED_CROSS, 2 * it[4] + 4, 2)
                        elif it[5] == "s":
                            cv2.rectangle(img, (p[0] - it[4], p[1] - it[4]), (p[0] + it[4], p[1] + it[4]), it[3], -1)
                        else:
                            cv2.circle(img, p, it[4], it[3], -1, cv2.LINE_AA)
        del clip
        x = ml + 8
        y = mt + 16
        for label, colour, kind in self._legend:
            if kind == "line":
                cv2.line(img, (x, y - 4), (x + 16, y - 4), colour, 2)
            else:
                cv2.circle(img, (x + 8, y - 4), 4, colour, -1)
            cv2.putText(img, label, (x + 22, y), FONT, 0.38, colour if colour != GREY else BLACK, 1, cv2.LINE_AA)
            y += 15
        return img


def pad(img: np.ndarray, h: int | None = None, w: int | None = None) -> np.ndarray:
    """White padding to at least ``h`` x ``w``."""
    H, W = img.shape[:2]
    h, w = max(h or H, H), max(w or W, W)
    out = np.full((h, w, 3), 255, np.uint8)
    out[:H, :W] = img
    return out


def hstack(imgs: Sequence[np.ndarray]) -> np.ndarray:
    h = max(i.shape[0] for i in imgs)
    return np.hstack([pad(i, h=h) for i in imgs])


def vstack(imgs: Sequence[np.ndarray]) -> np.ndarray:
    w = max(i.shape[1] for i in imgs)
    return np.vstack([pad(i, w=w) for i in imgs])


def titled(img: np.ndarray, text: str, *, height: int = 28, scale: float = 0.55) -> np.ndarray:
    band = np.full((height, img.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (6, height - 9), FONT, scale, BLACK, 1, cv2.LINE_AA)
    return np.vstack([band, img])


def image_grid(columns: Sequence[dict], row_names: Sequence[str], *, title: str, cell_w: int = 240) -> np.ndarray:
    """Rows x columns of pictures: ``columns = [{"label": str, "rows": [RGB or grey (H, W[, 3]) uint8]}]``."""
    cell_h = int(round(cell_w * 225 / 300))
    lab_w = 78
    head = 34
    W = lab_w + cell_w * len(columns) + 4 * len(columns)
    H = head + (cell_h + 4) * len(row_names) + 30
    img = np.full((H, W, 3), 255, np.uint8)
    lines = [title]
    per = max(30, (W - 12) // 9)  # about 9 px per character at this scale
    while len(lines[-1]) > per:
        cut = lines[-1].rfind(" ", 0, per)
        cut = per if cut <= 0 else cut
        lines[-1:] = [lines[-1][:cut], lines[-1][cut:].strip()]
    head += 18 * (len(lines) - 1)
    extra = np.full((18 * (len(lines) - 1), W, 3), 255, np.uint8)
    img = np.vstack([img, extra]) if len(lines) > 1 else img
    for i, line in enumerate(lines):
        cv2.putText(img, line, (6, 20 + 18 * i), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    for r, name in enumerate(row_names):
        y = head + r * (cell_h + 4)
        cv2.putText(img, name, (4, y + cell_h // 2), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
        for c, col in enumerate(columns):
            x = lab_w + c * (cell_w + 4)
            pic = col["rows"][r]
            if pic is None:
                cv2.rectangle(img, (x, y), (x + cell_w - 1, y + cell_h - 1), GREY, 1)
                cv2.putText(img, "no answer", (x + 10, y + cell_h // 2), FONT, 0.45, RED, 1, cv2.LINE_AA)
                continue
            if pic.ndim == 2:
                pic = np.repeat(pic[:, :, None], 3, axis=2)
            bgr = np.ascontiguousarray(pic[:, :, ::-1])
            img[y:y + cell_h, x:x + cell_w] = cv2.resize(bgr, (cell_w, cell_h), interpolation=cv2.INTER_AREA)
    yb = head + len(row_names) * (cell_h + 4) + 16
    for c, col in enumerate(columns):
        x = lab_w + c * (cell_w + 4)
        for k, line in enumerate(str(col["label"]).split("\n")[:2]):
            cv2.putText(img, line[:34], (x, yb + 12 * k - 4), FONT, 0.36, BLACK, 1, cv2.LINE_AA)
    return img


def write_png(img: np.ndarray, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        from scmr_mesh.errors import InputError

        raise InputError(f"could not write {path}")
    return path
