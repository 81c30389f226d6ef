"""Seeded synthetic scenes with exact ground truth (for the demo and the tests).

Each scene is drawn in a simple pinhole perspective: a horizon row, a
vanishing point, and a drivable surface whose borders converge on it.
Textures are multi-scale value noise, the lighting falls off with distance,
outdoor scenes get soft cast shadows (darker and bluer, still drivable), and
there are distractors (lane markings that *are* drivable, cars, rocks and
doors that are not), so segmentation is not trivial.  Then a camera model:
exposure and white balance per frame, fine surface grain, cos^4 lens
vignetting, optical blur, signal-dependent (shot + read) sensor noise.  Everything is derived
from ``numpy.random.default_rng(seed)``: the same ``(kind, seed, size)``
always gives the same pixels.

Examples
--------
>>> img, truth = make_scene("dirt_road", seed=3)
>>> img.shape, truth.shape, sorted(set(truth.ravel().tolist())) == [0, 255]
((225, 300, 3), (225, 300), True)
"""

from __future__ import annotations

import cv2
import numpy as np

from scmr_mesh.errors import InputError

SCENE_KINDS = ("structured_road", "dirt_road", "tunnel", "hallway", "desert")


def _noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """Smooth value noise in about [-1, 1] with features ~``cell`` pixels wide."""
    gh = max(2, int(np.ceil(h / cell)) + 2)
    gw = max(2, int(np.ceil(w / cell)) + 2)
    grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def _texture(rng, h, w, amps_cells) -> np.ndarray:
    out = np.zeros((h, w), np.float32)
    for amp, cell in amps_cells:
        out += amp * _noise(rng, h, w, cell)
    return out


def _paint(img: np.ndarray, where: np.ndarray, colour, tex: np.ndarray, light: np.ndarray | float = 1.0) -> None:
    """Fill ``where`` with ``colour`` times ``light`` plus the texture ``tex``."""
    h, w = img.shape[:2]
    col = np.asarray(colour, np.float32).reshape(1, 1, 3)
    lit = np.broadcast_to(np.asarray(light, np.float32), (h, w))[..., None]
    layer = col * lit + np.broadcast_to(tex, (h, w))[..., None]
    img[where] = layer[where]


def _between(xx, left, right):
    return (xx >= left) & (xx <= right)


def make_scene(kind: str, *, seed: int = 0, width: int = 300, height: int = 225) -> tuple[np.ndarray, np.ndarray]:
    """Draw a synthetic scene and its exact drivable mask.

    Parameters
    ----------
    kind : str
        One of :data:`SCENE_KINDS`.
    seed : int, keyword-only
        Random seed; the scene is a pure function of ``(kind, seed, width, height)``.
    width, height : int, keyword-only
        Image size (at least 16x16, at most 4000x4000).

    Returns
    -------
    rgb : (height, width, 3) uint8
    truth : (height, width) uint8
        255 = drivable, 0 = not.

    Raises
    ------
    InputError
        Unknown kind or unreasonable size.
    """
    if kind not in SCENE_KINDS:
        raise InputError(f"unknown scene kind {kind!r}; choose one of {', '.join(SCENE_KINDS)}")
    if not (16 <= int(width) <= 4000 and 16 <= int(height) <= 4000):
        raise InputError(f"scene size must be 16..4000 pixels per side, got {width}x{height}")
    w, h = int(width), int(height)
    rng = np.random.default_rng([SCENE_KINDS.index(kind), int(seed) & 0xFFFFFFFF])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.zeros((h, w, 3), np.float32)
    draw = {
        "structured_road": _structured_road,
        "dirt_road": _dirt_road,
        "tunnel": _tunnel,
        "hallway": _hallway,
        "desert": _desert,
    }[kind]
    truth = draw(rng, img, yy, xx, w, h)
    if kind in _OUTDOOR:
        _cast_shadows(rng, img, yy, xx, w, h)
    rgb = _camera(rng, img, yy, xx, w, h)
    return rgb, np.where(truth, 255, 0).astype(np.uint8)


#: Scenes lit by the sun, which get cast shadows.
_OUTDOOR = ("structured_road", "dirt_road", "desert")


def _cast_shadows(rng, img, yy, xx, w, h) -> None:
    """Soft shadows of things beside the path (trees, poles, buildings) across the lower image.

    Sunlit surfaces in shadow keep only the sky's light: darker and bluer (R 0.62, G 0.66,
    B 0.78 of the sunlit value), the ratios of skylight to sun plus skylight on a clear day.
    Shadows change no label: a shaded road is still road.
    """
    n = int(rng.integers(0, 3))
    if n == 0:
        return
    shade = np.zeros((h, w), np.float32)
    for _ in range(n):
        # a band from one side, slanted, with a wobbly soft edge
        y0 = rng.uniform(0.55, 0.95) * h
        slope = rng.uniform(-0.35, 0.35)
        thick = rng.uniform(0.04, 0.12) * h
        reach = rng.uniform(0.35, 0.8) * w
        from_left = rng.uniform() < 0.5
        along = xx if from_left else (w - 1 - xx)
        centre = y0 + slope * (xx - w / 2) + 4 * _noise(rng, 1, w, 15)[0][None, :]
        band = np.clip(1.0 - np.abs(yy - centre) / thick, 0, 1) * np.clip((reach - along) / 12.0, 0, 1)
        shade = np.maximum(shade, np.clip(band * 3.0, 0, 1))
    shade = cv2.GaussianBlur(shade, (0, 0), 2.0)
    gain = np.array([0.62, 0.66, 0.78], np.float32)
    factor = 1.0 - shade[..., None] * (1.0 - gain[None, None, :])
    img *= factor


def _camera(rng, img, yy, xx, w, h) -> np.ndarray:
    """What a cheap robot camera does to the scene's radiance: exposure and white balance,
    lens vignetting, optical blur, signal-dependent sensor noise, 8-bit quantisation."""
    # exposure and white balance of this frame
    img *= rng.uniform(0.85, 1.1) * rng.uniform(0.95, 1.05, 3).astype(np.float32)
    # fine grain of every surface (gravel, asphalt aggregate, dust): 1-2 px texture
    img *= (1.0 + 0.05 * _noise(rng, h, w, 1.5))[..., None]
    # vignetting: cos^4 falloff of a lens with a ~70 degree diagonal field of view
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / float((w / 2) ** 2 + (h / 2) ** 2)
    vig = 1.0 / (1.0 + 0.5 * r2) ** 2
    img *= vig[..., None]
    img = cv2.GaussianBlur(img, (3, 3), 0.7)
    # shot noise (variance grows with the signal) plus read noise
    sigma = np.sqrt(np.clip(img, 0, None) * 0.08 + 4.0)
    img += rng.normal(0.0, 1.0, img.shape).astype(np.float32) * sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------- geometry
def _perspective(rng, w, h, *, horizon=(0.36, 0.5), width_frac=(0.9, 1.4)):
    hz = h * rng.uniform(*horizon)
    vp = w * rng.uniform(0.42, 0.58)
    half = w * rng.uniform(*width_frac) / 2
    centre = w / 2 + w * rng.uniform(-0.08, 0.08)
    return hz, vp, centre - half, centre + half


def _edges_at(yy, hz, vp, bottom_x, h, curve=0.0):
    t = np.clip((yy - hz) / (h - hz), 0.0, 1.0)
    return vp + t * (bottom_x - vp) + curve * (1.0 - t) ** 2 * t * 4


def _sky(rng, img, yy, xx, w, h, hz, top=(120, 160, 215), low=(200, 215, 230)):
    t = np.clip(yy / max(hz, 1.0), 0, 1)[..., None]
    sky = np.asarray(top, np.float32) * (1 - t) + np.asarray(low, np.float32) * t
    sky += 6 * _noise(rng, h, w, 40)[..., None]
    sel = yy < hz
    img[sel] = sky[sel]


# ------------------------------------------------------------------- scenes
def _structured_road(rng, img, yy, xx, w, h):
    hz, vp, bl, br = _perspective(rng, w, h)
    _sky(rng, img, yy, xx, w, h, hz)
    # a band of buildings / trees along the horizon
    skyline = hz - h * (0.05 + 0.12 * (0.5 + 0.5 * _noise(rng, 1, w, 25)[0]))
    band = (yy >= skyline[None, :]) & (yy < hz)
    _paint(img, band, rng.choice([[90, 95, 85], [70, 90, 60], [120, 110, 105]]), _texture(rng, h, w, [(18, 6), (10, 2)]))
    ground = yy >= hz
    dist_light = 0.75 + 0.35 * np.clip((yy - hz) / (h - hz), 0, 1)
    side = rng.choice([[95, 125, 60], [150, 145, 135], [120, 130, 80]])
    _paint(img, ground, side, _texture(rng, h, w, [(14, 12), (10, 3)]), dist_light)
    left = _edges_at(yy, hz, vp, bl, h)
    right = _edges_at(yy, hz, vp, br, h)
    road = ground & _between(xx, left, right)
    asphalt = rng.uniform(70, 115)
    tint = rng.uniform(-6, 6, 3)
    _paint(img, road, asphalt + tint, _texture(rng, h, w, [(8, 20), (5, 3)]) + 10 * _noise(rng, h, w, 60), dist_light)
    # lane markings (drivable): solid edge lines and a dashed centre line
    t = np.clip((yy - hz) / (h - hz), 0, 1)
    lw = 0.5 + 5.0 * t
    for edge in (left + lw * 1.5, right - lw * 1.5):
        img[road & (np.abs(xx - edge) < lw / 2)] = 215
    centre = (left + right) / 2
    dashes = (np.sin(1.0 / np.maximum(t, 0.02) * 2.2 + rng.uniform(0, 6)) > 0.2)
    img[road & dashes & (np.abs(xx - centre) < lw / 2)] = 225
    # a car ahead (not drivable), sometimes
    truth = road.copy()
    if rng.uniform() < 0.6:
        ty = rng.uniform(0.15, 0.4)
        cy = hz + ty * (h - hz)
        cw = (right - left)[int(min(cy, h - 1)), 0] * rng.uniform(0.25, 0.35)
        cx = float(centre[int(min(cy, h - 1)), 0] + rng.choice([-1, 1]) * cw * 0.7)
        ch = cw * 0.8
        car = (np.abs(xx - cx) < cw / 2) & (yy > cy - ch) & (yy < cy)
        colour = rng.choice([[160, 30, 30], [30, 40, 120], [200, 200, 205], [25, 25, 25]])
        _paint(img, car, colour, _texture(rng, h, w, [(10, 4)]))
        img[car & (yy > cy - ch * 0.25)] *= 0.35  # shadowed lower body / wheels
        truth &= ~car
    return truth


def _dirt_road(rng, img, yy, xx, w, h):
    hz, vp, bl, br = _perspective(rng, w, h, horizon=(0.3, 0.45), width_frac=(0.55, 0.9))
    _sky(rng, img, yy, xx, w, h, hz, top=(150, 175, 210), low=(215, 220, 225))
    ground = yy >= hz
    light = 0.8 + 0.3 * np.clip((yy - hz) / (h - hz), 0, 1)
    grass = rng.choice([[85, 120, 45], [110, 125, 60], [70, 100, 50]])
    _paint(img, ground, grass, _texture(rng, h, w, [(20, 15), (18, 3), (10, 1.5)]), light)
    curve = w * rng.uniform(-0.25, 0.25)
    wobble = 6 * _noise(rng, h, 1, 12)[:, :1]
    left = _edges_at(yy, hz, vp, bl, h, curve) + wobble
    right = _edges_at(yy, hz, vp, br, h, curve) - wobble
    track = ground & _between(xx, left, right) & (yy >= hz + 2)
    dirt = np.array([rng.uniform(140, 175), rng.uniform(110, 135), rng.uniform(75, 95)])
    # wheel ruts: darker stripes inside the track
    t = np.clip((yy - hz) / (h - hz), 0, 1)
    rut = np.zeros((h, w), np.float32)
    for frac in (0.25, 0.75):
        rx = left + frac * (right - left)
        rut -= 18 * np.exp(-(((xx - rx) / (1 + 8 * t)) ** 2))
    _paint(img, track, dirt, _texture(rng, h, w, [(14, 10), (8, 2)]) + rut, light)
    # tufts of grass in the middle of the far track
    return track


def _tunnel(rng, img, yy, xx, w, h):
    hz = h * rng.uniform(0.42, 0.55)
    vp = w * rng.uniform(0.4, 0.6)
    # dark end of the tunnel
    img[...] = rng.uniform(10, 25)
    t = np.clip((yy - hz) / (h - hz), 0, 1)
    floor_l = _edges_at(yy, hz, vp, -w * rng.uniform(0.05, 0.25), h)
    floor_r = _edges_at(yy, hz, vp, w * rng.uniform(1.05, 1.25), h)
    # walls and arch: distance from the vanishing point in a squashed metric
    r = np.sqrt(((xx - vp) / (w * 0.55)) ** 2 + ((yy - hz) / (h * 0.6)) ** 2)
    light = np.clip(0.25 + 0.9 * r, 0, 1.2)
    rock = rng.choice([[105, 95, 85], [90, 90, 95], [120, 105, 80]])
    wall = r > 0.08
    _paint(img, wall, rock, _texture(rng, h, w, [(25, 8), (15, 2)]), light)
    floor = (yy >= hz) & _between(xx, floor_l, floor_r) & (r > 0.08)
    fcol = np.array(rock) * rng.uniform(0.7, 0.9) + rng.uniform(-10, 10, 3)
    # lamps every few metres light the floor fairly evenly: a gentle falloff with
    # distance and pools of light under each lamp
    depth = 1.0 / np.maximum(t, 0.03)
    pools = 0.12 * np.cos(depth * 2.0 + rng.uniform(0, 6)) ** 2
    flight = 0.65 + 0.45 * t + pools
    _paint(img, floor, fcol, _texture(rng, h, w, [(10, 12), (6, 2)]), flight)
    # a dark gutter where the floor meets the wall
    for edge in (floor_l, floor_r):
        img[(yy >= hz) & (np.abs(xx - edge) < 0.5 + 2.5 * t) & (r > 0.08)] *= 0.45
    # lamps along the crown
    for k in range(5):
        d = (k + 1) / 6
        ly = hz - d * h * 0.45
        lx = vp + rng.uniform(-0.03, 0.03) * w
        img[(((xx - lx) ** 2 + (yy - ly) ** 2) < (1.5 + 5 * d) ** 2)] = 250
    # a puddle-free rail-less floor: the drivable area is the floor itself
    return floor


def _hallway(rng, img, yy, xx, w, h):
    hz = h * rng.uniform(0.42, 0.5)
    vp = w * rng.uniform(0.4, 0.6)
    t = np.clip((yy - hz) / (h - hz), 0, 1)
    floor_l = _edges_at(yy, hz, vp, w * rng.uniform(-0.15, 0.1), h)
    floor_r = _edges_at(yy, hz, vp, w * rng.uniform(0.9, 1.15), h)
    wall_col = rng.choice([[200, 195, 180], [180, 190, 200], [215, 210, 200]])
    img[...] = wall_col
    img += _texture(rng, h, w, [(4, 20), (3, 3)])[..., None]
    # ceiling darker, with light panels
    ceil = yy < hz - (hz - 0) * 0.0 - np.abs(xx - vp) * (hz / (w * 0.9))
    img[ceil] *= 0.85
    # end wall
    end = (np.abs(xx - vp) < w * 0.06) & (np.abs(yy - hz + h * 0.03) < h * 0.08)
    img[end] = np.array(wall_col) * 0.6
    floor = (yy >= hz) & _between(xx, floor_l, floor_r)
    fcol = rng.choice([[150, 120, 90], [120, 125, 130], [170, 160, 140]])
    _paint(img, floor, fcol, _texture(rng, h, w, [(6, 15), (4, 2)]), 0.75 + 0.35 * t)
    # tile grid lines in perspective
    depth = 1.0 / np.maximum(t, 1e-3)
    rows = (np.mod(depth * 1.5, 1.0) < 0.06 * np.maximum(depth, 1) ** 0.2) & floor
    u = (xx - vp) / np.maximum(t, 1e-3)
    cols = (np.mod(u / 40.0, 1.0) < 0.05) & floor
    img[rows | cols] *= 0.9  # grout between the tiles
    # skirting boards (not drivable: they are on the wall side of the edge)
    for edge, sgn in ((floor_l, -1), (floor_r, 1)):
        skirt = (yy >= hz) & (np.abs(xx - (edge + sgn * (1 + 4 * t))) < (1 + 4 * t)) & ~floor
        img[skirt] = 60
    # doors on the walls
    for k in range(int(rng.integers(1, 4))):
        side = rng.choice([-1, 1])
        d = rng.uniform(0.3, 0.8)
        edge = (floor_l if side < 0 else floor_r)
        dy = hz + d * (h - hz)
        dx = float(edge[int(min(dy, h - 1)), 0]) + side * 3
        dwid = 6 + 30 * d
        door = (np.abs(xx - (dx + side * dwid / 2)) < dwid / 2) & (yy < dy) & (yy > dy - (dy - hz) * 3.2) & ~floor
        img[door] = rng.choice([[110, 70, 40], [70, 80, 100], [140, 140, 140]])
    return floor


def _desert(rng, img, yy, xx, w, h):
    hz = h * rng.uniform(0.28, 0.42)
    _sky(rng, img, yy, xx, w, h, hz, top=(140, 170, 210), low=(225, 215, 200))
    ground = yy >= hz
    t = np.clip((yy - hz) / (h - hz), 0, 1)
    sand = np.array([rng.uniform(190, 215), rng.uniform(160, 180), rng.uniform(110, 135)])
    dunes = 25 * np.sin(xx / (25 + 40 * t) + 3 * _noise(rng, h, w, 50)) * (0.3 + 0.7 * t)
    _paint(img, ground, sand, _texture(rng, h, w, [(10, 18), (8, 2)]) + dunes, 0.85 + 0.2 * t)
    # far mountains above the horizon
    ridge = hz - h * (0.04 + 0.06 * (0.5 + 0.5 * _noise(rng, 1, w, 40)[0]))
    hills = (yy >= ridge[None, :]) & (yy < hz)
    _paint(img, hills, [160, 130, 110], _texture(rng, h, w, [(10, 8)]))
    truth = ground.copy()
    # rocks: dark blobs standing on the ground, sized by distance
    rock_tex = _texture(rng, h, w, [(18, 3)])
    for _ in range(int(rng.integers(3, 8))):
        d = rng.uniform(0.15, 0.85)
        ry = hz + d * (h - hz)
        rx = rng.uniform(0, w)
        rr = 3 + 22 * d
        rock = ((xx - rx) / rr) ** 2 + ((yy - ry) / (rr * 0.6)) ** 2 < 1
        rock &= ground
        _paint(img, rock, [95, 75, 60], rock_tex, 0.8 + 0.4 * np.clip((ry - yy) / rr, 0, 1))
        truth &= ~rock
    return truth
