"""Scoring drivable masks against labelled images (``scmr eval``).

The data folder holds a ``manifest.json`` in the ``scmr-roads-manifest/1``
format (see ``../shared/data/roads/manifest.json``): a list of items with
``image``, ``mask``, ``dataset``, ``mask_mode`` (``"gray"`` or ``"rgb"``, RGB
colours in RGB order), ``road`` (values that are road) and ``ignore``
(values left out of scoring), and optionally ``obstacles`` (an object naming
classes such as ``"person"`` with the mask values that hold them, for the
report of obstacles painted drivable; without it the shared datasets' own
label encodings are used, :data:`KNOWN_OBSTACLES`).  Every image is scored at
300x225: the prediction is made at that size and the ground truth is resized
with nearest-neighbour interpolation.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from scmr_mesh.errors import ConfigError, InputError, ScmrError
from scmr_mesh.imaging.codec import FRAME_HEIGHT, FRAME_WIDTH, load_frame

log = logging.getLogger(__name__)

METRICS = ("iou", "f1", "precision", "recall")


@dataclass(frozen=True)
class Item:
    """One labelled image of a manifest."""

    image: Path
    mask: Path
    dataset: str
    mask_mode: str
    road: tuple
    ignore: tuple
    #: ``((name, values), ...)``: the obstacle classes of this item's mask (may be empty)
    obstacles: tuple = ()


#: The obstacle classes the report of obstacles painted drivable names (issue 27: a robot drives
#: where the mask is green; green on a person is the costliest error the pipeline can make).
OBSTACLE_CLASSES = ("person", "cyclist", "vehicle", "pole")

_UMICH_OBSTACLES = {  # id masks (all three channels the class id) and colour masks (RGB), SOURCES.md
    "person": [[8, 8, 8], [157, 199, 194]],
    "cyclist": [[9, 9, 9], [237, 61, 55]],   # the repo's class "bike"
    "vehicle": [[7, 7, 7], [20, 99, 143]],
    "pole": [[5, 5, 5], [237, 9, 28]],
}

#: The obstacle classes of the shared datasets' label encodings, by ``(dataset, mask_mode)``
#: (``../shared/data/roads/SOURCES.md``): CamVid's SegNet classes (2 Pole, 8 Car, 9 Pedestrian,
#: 10 Bicyclist), RELLIS-3D's ontology (5 pole, 8 vehicle, 17 person), UMich-CURLY's classes
#: (5 pole, 7 vehicle, 8 human, 9 bike).  KITTI's and ORFD's masks here are binary: no classes.
#: An item's own ``obstacles`` field replaces these (``{}`` turns the report off for it).
KNOWN_OBSTACLES: dict[tuple[str, str], dict[str, list]] = {
    ("camvid", "gray"): {"person": [9], "cyclist": [10], "vehicle": [8], "pole": [2]},
    ("rellis3d", "gray"): {"person": [17], "vehicle": [8], "pole": [5]},
    ("umich_campus_sidewalk", "rgb"): _UMICH_OBSTACLES,
    ("umich_forest_traversable", "rgb"): _UMICH_OBSTACLES,
}


def _obstacles(it: dict, mode: str, dataset: str, road: tuple) -> tuple:
    spec = it["obstacles"] if "obstacles" in it else KNOWN_OBSTACLES.get((dataset, mode), {})
    if not isinstance(spec, dict):
        raise TypeError(f"expected an object of class name -> list of mask values, got {type(spec).__name__}")
    out = []
    for name, vals in spec.items():
        if not (isinstance(name, str) and name):
            raise ValueError(f"a class name must be a non-empty string, got {name!r}")
        values = _values(vals, mode)
        both = [v for v in values if v in road]
        if both:
            raise ValueError(f"class {name!r} lists the road value {list(both[0]) if mode == 'rgb' else both[0]}; "
                             "a pixel is road or an obstacle, not both")
        out.append((name, values))
    return tuple(out)


def load_manifest(folder: str | Path) -> list[Item]:
    """Read and validate ``folder/manifest.json``.

    Raises
    ------
    InputError
        The folder or manifest is missing.
    ConfigError
        The manifest is not valid JSON or an item is malformed; the message
        names the item and field.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"data folder not found: {folder} (expected a folder holding manifest.json)")
    path = folder / "manifest.json"
    if not path.is_file():
        raise InputError(f"no manifest.json in {folder}; expected the format of shared/data/roads/manifest.json")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    items = doc.get("items") if isinstance(doc, dict) else None
    if not isinstance(items, list) or not items:
        raise ConfigError(f"{path}: expected an object with a non-empty 'items' list")
    out = []
    for i, it in enumerate(items):
        where = f"{path}: items[{i}]"
        if not isinstance(it, dict):
            raise ConfigError(f"{where}: expected an object, got {type(it).__name__}")
        for key in ("image", "mask", "road"):
            if key not in it:
                raise ConfigError(f"{where}: missing field {key!r}")
        mode = it.get("mask_mode", "gray")
        if mode not in ("gray", "rgb"):
            raise ConfigError(f"{where}: mask_mode must be 'gray' or 'rgb', got {mode!r}")
        try:
            road = _values(it["road"], mode)
            ignore = _values(it.get("ignore", []), mode)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: bad road/ignore values ({exc})") from None
        if not road:
            raise ConfigError(f"{where}: 'road' lists no values")
        dataset = str(it.get("dataset", "default"))
        try:
            obstacles = _obstacles(it, mode, dataset, road)
        except (TypeError, ValueError) as exc:
            example = '{"person": [9]}' if mode == "gray" else '{"person": [[157, 199, 194]]}'
            raise ConfigError(f"{where}: bad 'obstacles' ({exc}); expected e.g. {example}") from None
        out.append(
            Item(
                image=folder / str(it["image"]),
                mask=folder / str(it["mask"]),
                dataset=dataset,
                mask_mode=mode,
                road=road,
                ignore=ignore,
                obstacles=obstacles,
            )
        )
    return out


def _values(vals, mode: str) -> tuple:
    """A manifest's list of mask values: integers 0-255 (``gray``) or ``[R, G, B]`` lists of them."""
    if not isinstance(vals, list):
        raise TypeError(f"expected a list, got {type(vals).__name__}")

    def byte(v) -> int:
        # masks are read as 8 bits a channel: any other value would match nothing, silently
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
            raise ValueError(f"mask values are integers 0-255, got {v!r}")
        return v

    if mode == "gray":
        return tuple(byte(v) for v in vals)
    out = []
    for v in vals:
        if not (isinstance(v, list) and len(v) == 3):
            raise ValueError(f"rgb values must be [R, G, B] lists, got {v!r}")
        out.append(tuple(byte(c) for c in v))
    return tuple(out)


def _read_mask(item: Item) -> np.ndarray:
    data = None
    try:
        data = item.mask.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read mask {item.mask}: {exc.strerror or exc}") from None
    flag = cv2.IMREAD_GRAYSCALE if item.mask_mode == "gray" else cv2.IMREAD_COLOR
    m = cv2.imdecode(np.frombuffer(data, np.uint8), flag) if data else None
    if m is None:
        raise InputError(f"mask {item.mask} is not a readable image")
    if item.mask_mode == "rgb":
        m = cv2.cvtColor(m, cv2.COLOR_BGR2RGB)
    return m


def truth_at_frame(item: Item) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth of an item at 300x225.

    Returns
    -------
    road : (225, 300) bool
    valid : (225, 300) bool
        False where the mask holds an ``ignore`` value.
    """
    road, valid, _ = labels_at_frame(item, obstacles=False)
    return road, valid


def labels_at_frame(item: Item, *, obstacles: bool = True) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`truth_at_frame`'s ``(road, valid)`` and each of the item's obstacle classes at 300x225.

    The third value maps each name of ``item.obstacles`` to a (225, 300) bool mask (empty
    with ``obstacles`` False or an item without obstacle classes).
    """
    m = _read_mask(item)
    m = cv2.resize(m, (FRAME_WIDTH, FRAME_HEIGHT), interpolation=cv2.INTER_NEAREST)

    def where(values: tuple) -> np.ndarray:
        if item.mask_mode == "gray":
            return np.isin(m, values) if values else np.zeros(m.shape, bool)
        hit = np.zeros(m.shape[:2], bool)
        for c in values:
            hit |= np.all(m == np.array(c, np.uint8), axis=2)
        return hit

    classes = {name: where(values) for name, values in item.obstacles} if obstacles else {}
    return where(item.road), ~where(item.ignore), classes


#: Obstacles painted drivable are counted on the pixels at least this far (at 300x225) inside their
#: label: the labels' own edges and the road model's 150x112 working frame disagree by about that
#: much, and an edge pixel of a car beside the road is not the car painted drivable.
OBSTACLE_MARGIN = 2
#: A frame counts as a hit for a class when at least this many of that class's inner pixels are
#: green (a patch of about 3x4 pixels at 300x225: a wheel, a leg).
OBSTACLE_HIT_PX = 10


def obstacle_green(pred: np.ndarray, obstacle: np.ndarray, valid: np.ndarray | None = None) -> tuple[int, int]:
    """``(inner, green)``: an obstacle class's pixels at least :data:`OBSTACLE_MARGIN` inside its
    label (the frame's edge is not the label's edge), and how many of them ``pred`` paints drivable.

    >>> car = np.zeros((20, 20), bool); car[5:15, 5:15] = True
    >>> pred = np.zeros((20, 20), np.uint8); pred[10:] = 255
    >>> obstacle_green(pred, car)      # a 6x6 inner block, its lower 3 rows green
    (36, 18)
    """
    inner = obstacle_inner(obstacle, valid)
    return int(np.count_nonzero(inner)), int(np.count_nonzero(inner & (np.asarray(pred) != 0)))


def obstacle_inner(obstacle: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """The (valid) pixels of an obstacle class at least :data:`OBSTACLE_MARGIN` inside its label
    (:func:`obstacle_green`'s, made once per frame for every mask scored on it)."""
    k = 2 * OBSTACLE_MARGIN + 1
    inner = cv2.erode(np.asarray(obstacle, np.uint8), np.ones((k, k), np.uint8)) > 0
    if valid is not None:
        inner &= valid
    return inner


def obstacle_classes(classes: dict[str, np.ndarray], valid: np.ndarray) -> dict[str, tuple[int, int, np.ndarray]]:
    """Per obstacle class of a frame: its labelled (valid) pixels, its inner pixels and their mask
    (:func:`obstacle_inner`), made once per frame for every mask scored on it."""
    out = {}
    for c, m in classes.items():
        inner = obstacle_inner(m, valid)
        out[c] = (int(np.count_nonzero(m & valid)), int(np.count_nonzero(inner)), inner)
    return out


def obstacle_row(classes: dict[str, tuple[int, int, np.ndarray]], pred: np.ndarray) -> dict[str, list[int]]:
    """A mask's ``{class: [labelled, inner, green]}`` (the row entries :func:`obstacle_totals` sums)
    over a frame's :func:`obstacle_classes`."""
    green = np.asarray(pred) != 0
    return {c: [n, ni, int(np.count_nonzero(inner & green))] for c, (n, ni, inner) in classes.items()}


def score(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> dict[str, float]:
    """IoU, F1, precision and recall of a predicted mask over the valid pixels.

    Empty cases: with no predicted and no true road every metric is 1.0;
    otherwise a 0/0 ratio counts as 0.0.

    Parameters
    ----------
    pred, truth : (H, W) arrays, non-zero = road
    valid : (H, W) bool, optional

    Returns
    -------
    dict with keys ``iou``, ``f1``, ``precision``, ``recall``
    """
    p = np.asarray(pred) != 0
    t = np.asarray(truth) != 0
    if p.shape != t.shape:
        raise InputError(f"prediction shape {p.shape} differs from truth shape {t.shape}")
    if valid is not None:
        p = p & valid
        t = t & valid
    tp = int(np.count_nonzero(p & t))
    fp = int(np.count_nonzero(p & ~t))
    fn = int(np.count_nonzero(~p & t))
    if tp + fp + fn == 0:
        return {k: 1.0 for k in METRICS}

    def ratio(a: int, b: int) -> float:
        return a / b if b else 0.0

    return {
        "iou": ratio(tp, tp + fp + fn),
        "f1": ratio(2 * tp, 2 * tp + fp + fn),
        "precision": ratio(tp, tp + fp),
        "recall": ratio(tp, tp + fn),
    }


def bottom_half_mask() -> np.ndarray:
    """The "bottom half is road" baseline at 300x225."""
    m = np.zeros((FRAME_HEIGHT, FRAME_WIDTH), np.uint8)
    m[FRAME_HEIGHT // 2 :] = 255
    return m


def _mean(rows: list[dict]) -> dict[str, float]:
    return {k: float(np.mean([r[k] for r in rows])) if rows else 0.0 for k in METRICS}


def evaluate(
    folder: str | Path,
    *,
    mode: str = "best",
    baselines: bool = True,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Score ``mode`` (and the baselines) on every item of a manifest.

    Returns
    -------
    dict
        ``{"mode", "images": [{"image", "dataset", "iou", "f1", "precision",
        "recall"}], "mean": {...}, "per_dataset": {name: {...}}, "baselines":
        {"bottom_half": {...mean...}, "thesis": {...mean...}}}``; each baseline
        also carries its ``per_dataset`` means.  ``"obstacles"``: for ``mode`` and each
        baseline, per dataset and obstacle class (:func:`obstacle_totals`), the inner pixels
        of the class painted drivable; each image row of ``mode`` carries its own
        ``"obstacles": {class: [labelled, inner, green]}``.
    """
    from scmr_mesh.imaging.pipeline import segment_drivable

    items = load_manifest(folder)
    others = ["bottom_half", "thesis"] if baselines else []
    others = [o for o in others if o != mode]
    rows: list[dict] = []
    base_rows: dict[str, list[dict]] = {o: [] for o in others}
    skipped: list[dict] = []
    for i, item in enumerate(items):
        if progress:
            progress(i, len(items), item.image.name)
        try:
            rgb = load_frame(item.image)
            road, valid, classes = labels_at_frame(item)
        except ScmrError as exc:  # one unreadable pair must not sink the whole evaluation
            skipped.append({"image": item.image.name, "error": str(exc)})
            continue

        inner = obstacle_classes(classes, valid)   # the erosion once, not once per mask

        def row(pred: np.ndarray) -> dict:
            return {"image": item.image.name, "dataset": item.dataset, **score(pred, road, valid),
                    "obstacles": obstacle_row(inner, pred)}

        rows.append(row(segment_drivable(rgb, mode=mode).mask))
        for o in others:
            base_rows[o].append(row(bottom_half_mask() if o == "bottom_half" else segment_drivable(rgb, mode=o).mask))
    if progress:
        progress(len(items), len(items), "")
    if not rows:
        raise InputError(
            f"{folder}: none of the {len(items)} manifest item(s) could be read "
            f"(first problem: {skipped[0]['error'] if skipped else 'none'})"
        )
    out = {
        "mode": mode,
        "skipped": skipped,
        "images": rows,
        "mean": _mean(rows),
        "per_dataset": _per_dataset(rows),
        "baselines": {o: {**_mean(r), "per_dataset": _per_dataset(r)} for o, r in base_rows.items()},
        "obstacles": {mode: obstacle_totals(rows), **{o: obstacle_totals(r) for o, r in base_rows.items()}},
    }
    for r in base_rows.values():   # the baselines' per-image counts are in their totals
        for b in r:
            b.pop("obstacles")
    return out


def obstacle_totals(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """Per dataset and obstacle class, summed over the image rows that label the class.

    Each row's ``"obstacles"`` maps a class to ``[labelled, inner, green]``.  Each entry:
    ``labelled`` (the class's scored pixels) and ``labelled_frames`` (images with any), ``inner``
    (those at least :data:`OBSTACLE_MARGIN` inside the label: a class thinner than
    ``2 * OBSTACLE_MARGIN + 1`` pixels, a far pole or person, has none), ``green`` (how many inner
    pixels the mask paints drivable), ``share`` (green / inner; 0.0 when inner is 0), ``frames``
    (images with inner pixels of the class) and ``hit`` (images with at least
    :data:`OBSTACLE_HIT_PX` of them green).  Datasets without obstacle classes are left out.

    >>> rows = [{"dataset": "a", "obstacles": {"person": [80, 50, 10]}},
    ...         {"dataset": "a", "obstacles": {"person": [60, 40, 9]}},
    ...         {"dataset": "b", "obstacles": {"person": [3, 0, 0]}}]
    >>> t = obstacle_totals(rows)
    >>> t["a"]["person"] == {"labelled": 140, "labelled_frames": 2, "inner": 90, "green": 19,
    ...                      "frames": 2, "hit": 1, "share": 19 / 90}
    True
    >>> t["b"]["person"]["frames"], t["b"]["person"]["labelled_frames"], t["b"]["person"]["share"]
    (0, 1, 0.0)
    """
    out: dict[str, dict[str, dict]] = {}
    for r in rows:
        for name, (labelled, inner, green) in r.get("obstacles", {}).items():
            e = out.setdefault(r["dataset"], {}).setdefault(name, dict.fromkeys(_COUNTS, 0))
            e["labelled"] += labelled
            e["labelled_frames"] += labelled > 0
            e["inner"] += inner
            e["green"] += green
            e["frames"] += inner > 0
            e["hit"] += green >= OBSTACLE_HIT_PX
    for per in out.values():
        _add_shares(per)
    return {d: dict(sorted(per.items(), key=lambda kv: _class_order(kv[0]))) for d, per in sorted(out.items())}


def _add_shares(classes: dict[str, dict]) -> dict[str, dict]:
    for e in classes.values():
        e["share"] = e["green"] / e["inner"] if e["inner"] else 0.0
    return classes


_COUNTS = ("labelled", "labelled_frames", "inner", "green", "frames", "hit")


def _sum_over_datasets(per: dict[str, dict[str, dict]]) -> dict[str, dict]:
    """Per class, :func:`obstacle_totals`' entries summed over the datasets."""
    out: dict[str, dict] = {}
    for classes in per.values():
        for c, e in classes.items():
            t = out.setdefault(c, dict.fromkeys(_COUNTS, 0))
            for k in _COUNTS:
                t[k] += e[k]
    return _add_shares(out)


def _class_order(name: str) -> tuple:
    return (OBSTACLE_CLASSES.index(name), "") if name in OBSTACLE_CLASSES else (len(OBSTACLE_CLASSES), name)


def _per_dataset(rows: list[dict]) -> dict[str, dict[str, float]]:
    names = sorted({r["dataset"] for r in rows})
    return {n: {**_mean([r for r in rows if r["dataset"] == n]), "n": sum(r["dataset"] == n for r in rows)} for n in names}


def format_table(result: dict) -> str:
    """A plain-text table of an :func:`evaluate` result."""
    lines = [f"{'image':48s} {'dataset':11s} {'IoU':>6s} {'F1':>6s} {'prec':>6s} {'recall':>6s}"]
    for r in result["images"]:
        lines.append(
            f"{r['image'][:48]:48s} {r['dataset'][:11]:11s} {r['iou']:6.3f} {r['f1']:6.3f} "
            f"{r['precision']:6.3f} {r['recall']:6.3f}"
        )
    m = result["mean"]
    lines.append(f"{'mean (' + result['mode'] + ')':60s} {m['iou']:6.3f} {m['f1']:6.3f} {m['precision']:6.3f} {m['recall']:6.3f}")
    lines.append("")
    names = list(result["per_dataset"])
    header = f"{'mean IoU per dataset':22s} " + " ".join(f"{n[:11]:>11s}" for n in names) + f" {'all':>7s}"
    lines.append(header)
    cols = [(result["mode"], result)] + [(k, v) for k, v in result["baselines"].items()]
    for name, res in cols:
        pd = res["per_dataset"]
        vals = " ".join(f"{pd[n]['iou']:11.3f}" if n in pd else f"{'-':>11s}" for n in names)
        mean_iou = res["mean"]["iou"] if "mean" in res else res["iou"]
        lines.append(f"{name:22s} {vals} {mean_iou:7.3f}")
    lines.append("")
    lines.append(f"{'precision / recall':22s} " + " ".join(f"{n[:11]:>11s}" for n in names) + f" {'all':>11s}")
    for name, res in cols:
        pd, mean = res["per_dataset"], res["mean"] if "mean" in res else res
        vals = " ".join(f"{pd[n]['precision']:5.3f}/{pd[n]['recall']:5.3f}" if n in pd else f"{'-':>11s}" for n in names)
        lines.append(f"{name:22s} {vals} {mean['precision']:5.3f}/{mean['recall']:5.3f}")
    lines.extend(format_obstacles(result.get("obstacles", {})))
    return "\n".join(lines)


def format_obstacles(obstacles: dict, *, group: str = "dataset") -> list[str]:
    """The table lines of :func:`evaluate`'s ``"obstacles"`` (none when no dataset labels obstacles).

    >>> e = {"labelled": 140, "labelled_frames": 2, "inner": 90, "green": 19, "frames": 2, "hit": 1,
    ...      "share": 19 / 90}
    >>> lines = format_obstacles({"best": {"a": {"person": e}, "b": {"person": e}}})
    >>> [" ".join(x.split()) for x in lines[-3:]]
    ['a person 0.211 ( 1/ 2) 90 / 140', 'b person 0.211 ( 1/ 2) 90 / 140', '(all) person 0.211 ( 2/ 4) 180 / 280']
    """
    modes = list(obstacles)
    # a class no frame of a dataset shows inside its margin has nothing to say; "(all)" sums a
    # class over the datasets
    pairs = sorted({(d, c) for m in modes for d, per in obstacles[m].items() for c, e in per.items() if e["frames"]},
                   key=lambda dc: (dc[0], _class_order(dc[1])))
    if not pairs:
        return []
    obstacles = {m: {**per, "(all)": _sum_over_datasets(per)} for m, per in obstacles.items()}
    pairs += sorted({("(all)", c) for _, c in pairs}, key=lambda dc: _class_order(dc[1]))
    dw = max(len(group), *(len(d) for d, _ in pairs))
    cw = max(len("class"), *(len(c) for _, c in pairs))
    lines = ["", f"obstacles painted drivable: share of their pixels >= {OBSTACLE_MARGIN} px inside the label "
                 f"(frames with >= {OBSTACLE_HIT_PX} such pixels green / frames with such pixels); "
                 "thinner parts are not counted (last column: inner / labelled pixels)",
             f"{group:{dw}s} {'class':{cw}s} " + " ".join(f"{m[:16]:>16s}" for m in modes)
             + f" {'inner / labelled':>20s}"]
    for d, c in pairs:
        cells, cover = [], ""
        for m in modes:
            e = obstacles[m].get(d, {}).get(c)
            cells.append(f"{e['share']:5.3f} ({e['hit']:2d}/{e['frames']:2d})" if e else "-")
            if e:
                cover = f"{e['inner']} / {e['labelled']}"
        lines.append(f"{d:{dw}s} {c:{cw}s} " + " ".join(f"{x:>16s}" for x in cells) + f" {cover:>20s}")
    return lines


#: The values :func:`cross_validate` chooses ``best``'s constants from (every combination).
CV_GRID: dict[str, tuple] = {
    # SRM Q 4096 and sunlit 120 were in the grid until issue 27 and no fold of the 60-image
    # cross-validation chose them; they left to make room for the abstention's constants.
    # p 0.95, gap 10 and lateral 1/3 were in the 1152-combination run that brought `lateral`
    # (docs/ACCURACY.md) and no fold chose them, so leaving them out changes no choice
    "q": (2048.0,),
    "p": (0.9, 0.99),
    "frac": (0.3, 0.5),
    "gap": (20,),
    "shade": (0.0, 0.2),
    "sunlit": (80.0,),
    "opening": (0, 9),
    "reach": (0.0, 0.35),
    # cap 0.4 left when a fragmented ground became a seed (issue 27): the folds then chose it
    # for the forest floor's two frames whose seed is not ground (a tie on every other image),
    # and as the default it lowered the synthetic tunnel below issue 27's 0.85 (0.865 -> 0.847)
    # and the structured road 0.746 -> 0.721 (docs/ACCURACY.md)
    "cap": (0.5,),
    "standing": (False, True),
    "lateral": (0.0, 0.25),
    # the weak-border join (issue 27, 2026-11-28): 0 = off; with the one-sided shade term the folds
    # choose 4 (the campus sidewalk) and 6 (the others); before it, 0 / 4 / 6
    "weak": (0.0, 4.0, 6.0),
    # the cut along the road's boundaries (issue 27, 2026-11-29): 0 = off, or the shortest edge
    # as a share of the height; 0.25 was in the first prototype's 1152-combination run and no fold
    # chose it (CamVid's fold chose 0 there, the others 0.3), so it left; now every fold chooses 0.3
    "boundary": (0.0, 0.3),
    # `rough` (the cut of rough surfaces, issue 27, 2026-11-29) is not in the grid: every fold chose
    # 1.75 (0.830 -> 0.833 over images, 0.786 -> 0.795 over datasets), but no labelled frame is
    # blurred in part, and on the shared frames with part of the frame blurred it cut the sharp road;
    # its blur guard keeps some blurs and not others (a strong drop over the bottom centre,
    # docs/ACCURACY.md); it stays 0, an option
}

#: The operating point: cross-validation chooses, among the combinations whose mean precision on
#: the training images is at least this, the one with the highest mean IoU there (issue 27: a
#: robot drives where the mask is green, so green where it cannot drive is the costly error).
#: The target is 0.85 on held-out data; precision on the training images overstates it, hence
#: the margin.  0.88 was picked after comparing 0.85 / 0.88 / 0.90 on the cross-validation
#: itself (docs/ACCURACY.md gives all three), so its cross-validated figures are a little optimistic.
MIN_PRECISION = 0.88

#: The synthetic scenes' requirements on the shipped constants (issue 27 item 3; the demo's
#: overlays are these scenes): over seeds :data:`SYNTHETIC_SEEDS` of every kind of
#: :func:`~scmr_mesh.imaging.synthetic.make_scene`, mean precision >= :data:`SYNTHETIC_PRECISION`
#: and mean IoU >= :data:`SYNTHETIC_IOU_TARGET`, or, for the kinds still below that target, >= the
#: floor each holds today (:data:`SYNTHETIC_KNOWN_BELOW`, empty since 2026-11-29: every kind meets
#: the target with the defaults, seeds 0-7: desert 0.852 since open ground is cut at its horizon
#: line and its front counts the same sand running on in shade below that line (0.781 before;
#: seeds 8-200, never used to choose anything, 0.722 -> 0.792, docs/ACCURACY.md); structured road
#: 0.855, dirt road 0.967, tunnel 0.911, hallway 0.959).
#: ``tests/test_imaging_synthetic_truth.py`` holds the defaults to them, and
#: :func:`cross_validate` lets every fold choose only among the combinations that meet them.
SYNTHETIC_SEEDS = range(8)
SYNTHETIC_IOU_TARGET = 0.85
SYNTHETIC_PRECISION = 0.85
SYNTHETIC_KNOWN_BELOW: dict[str, float] = {}


def synthetic_floor(kind: str) -> float:
    """The mean IoU the constants must reach on the synthetic scenes of ``kind``."""
    return SYNTHETIC_KNOWN_BELOW.get(kind, SYNTHETIC_IOU_TARGET)


def synthetic_fits(iou: dict, precision: dict) -> np.ndarray:
    """Which params meet the synthetic floors: every kind's mean IoU >= :func:`synthetic_floor` and
    mean precision >= :data:`SYNTHETIC_PRECISION` (``iou``, ``precision``: kind -> array over params).

    >>> synthetic_fits({"tunnel": np.array([0.9, 0.9, 0.8])}, {"tunnel": np.array([0.9, 0.8, 0.9])}).tolist()
    [True, False, False]
    """
    kinds = list(iou)
    fits = np.ones(len(iou[kinds[0]]) if kinds else 0, bool)
    for kind in kinds:
        fits &= (np.asarray(iou[kind]) >= synthetic_floor(kind)) & (np.asarray(precision[kind]) >= SYNTHETIC_PRECISION)
    return fits


def synthetic_scores(params_list: list, *, progress: Callable[[int, int, str], None] | None = None) -> dict:
    """Mean IoU and precision of ``best`` on the synthetic scenes, per kind, for each params.

    Returns ``{"iou": {kind: (n_params,) array}, "precision": {...}, "fits": (n_params,) bool}``
    (``fits``: :func:`synthetic_fits`).
    """
    from scmr_mesh.imaging.pipeline import best_masks
    from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene

    seeds = list(SYNTHETIC_SEEDS)
    iou = {k: np.zeros(len(params_list)) for k in SCENE_KINDS}
    precision = {k: np.zeros(len(params_list)) for k in SCENE_KINDS}
    total, done = len(SCENE_KINDS) * len(seeds), 0
    for kind in SCENE_KINDS:
        for seed in seeds:
            if progress:
                progress(done, total, f"synthetic {kind}:{seed}")
            done += 1
            img, truth = make_scene(kind, seed=seed)
            for ci, (mask, _c, _a) in enumerate(best_masks(img, params_list)):
                s = score(mask, truth)
                iou[kind][ci] += s["iou"] / len(seeds)
                precision[kind][ci] += s["precision"] / len(seeds)
    if progress:
        progress(total, total, "")
    return {"iou": iou, "precision": precision, "fits": synthetic_fits(iou, precision)}


def choose_combination(iou: np.ndarray, precision: np.ndarray, train: np.ndarray, min_precision: float,
                       allowed: np.ndarray | None = None) -> int:
    """The operating point: the combination with the best mean IoU over the ``train`` images.

    ``iou`` and ``precision`` are (combinations, images).  Only ``allowed`` combinations are
    candidates (all when None or when none is allowed); among them, those whose mean precision
    over ``train`` is at least ``min_precision`` (all of them when none is).  Ties go to the
    first combination, the grid's order.

    >>> iou = np.array([[0.9, 0.9], [0.8, 0.8], [0.7, 0.7]]); prec = np.array([[0.8, 0.8], [0.9, 0.9], [0.95, 0.95]])
    >>> train = np.array([True, True])
    >>> choose_combination(iou, prec, train, 0.0), choose_combination(iou, prec, train, 0.88)
    (0, 1)
    >>> choose_combination(iou, prec, train, 0.88, allowed=np.array([True, False, True]))
    2
    """
    ok = np.ones(iou.shape[0], bool) if allowed is None or not allowed.any() else allowed.copy()
    mean_iou = iou[:, train].mean(axis=1)
    precise = ok & (precision[:, train].mean(axis=1) >= min_precision)
    if precise.any():
        ok = precise
    return int(np.argmax(np.where(ok, mean_iou, -1.0)))



def _checked_grid(grid: dict, params_cls, min_precision: float, *, what: str) -> dict:
    """``grid`` (constant -> values) checked against ``params_cls``'s fields, with the precision floor."""
    grid = dict(grid)
    if not 0 <= min_precision <= 1:
        raise InputError(f"min_precision must be in [0, 1], got {min_precision}")
    fields = set(params_cls.__dataclass_fields__)
    for k, vals in grid.items():
        if k not in fields:
            raise InputError(f"{what}: unknown constant {k!r}; choose from {', '.join(sorted(fields))}")
        if not vals:
            raise InputError(f"{what}: no values for {k!r}")
    return grid

def cross_validate(
    folder: str | Path,
    *,
    grid: dict[str, tuple] | None = None,
    min_precision: float = MIN_PRECISION,
    synthetic: bool = True,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Leave-one-dataset-out cross-validation of ``best``'s constants.

    Every combination of ``grid`` (default :data:`CV_GRID`) is scored on every
    image (SRM runs once per image and Q).  For each dataset ``d``, the combination with the
    highest mean IoU over the images of the *other* datasets, among those whose mean precision
    there is at least ``min_precision`` (all, when none is; 0 = IoU alone), is chosen and
    scored on ``d``: that is ``d``'s cross-validated IoU, precision and recall.  The in-sample IoU is that of the
    combination chosen on all images (the shipped defaults, when they are up to
    date), and the bottom-half baseline is scored beside both.

    With ``synthetic`` (the default), every choice, the folds' and the in-sample one, is made
    only among the combinations that meet the synthetic scenes' floors (:func:`synthetic_scores`),
    the requirements the shipped defaults are held to: so each fold chooses as the defaults are
    chosen, and the cross-validated figures estimate the procedure that is shipped (before
    2026-11-28 a fold could choose constants that could never be shipped: CamVid's chose ``shade``
    0 and ``standing`` False, under which four of the five synthetic kinds fall below their floors).
    When only the in-sample constants are left to a fold, its figures are the in-sample ones and
    show nothing beyond them (docs/ACCURACY.md).  A grid none of whose combinations meets the
    floors is refused (:class:`~scmr_mesh.errors.InputError`).

    Returns
    -------
    dict
        ``{"grid", "combinations", "in_sample": {"params", "mean_iou"},
        "per_dataset": {d: {"n", "cv_iou", "cv_precision", "cv_recall", "cv_params",
        "in_sample_iou", "in_sample_precision", "in_sample_recall", "bottom_half_iou"}},
        "mean": {...same keys...}, "mean_of_datasets": {...}, "min_precision", "skipped",
        "synthetic": {"checked": True, "target", "floors": {kind: IoU}, "precision", "fit": how
        many combinations meet them, "in_sample": {kind: {"iou", "precision"}} of the in-sample
        choice} or {"checked": False}, "obstacles": {"cross-validated": ..., "in-sample": ...}}``
        (:func:`obstacle_totals` of each frame's mask under its fold's choice and under the
        in-sample one: the obstacles painted drivable; they do not enter the choice); means are
        over images (each image weighs the same) and over datasets.
    """
    import itertools

    from scmr_mesh.imaging.codec import load_frame as _load
    from scmr_mesh.imaging.pipeline import best_masks
    from scmr_mesh.imaging.road_model import RoadParams

    grid = _checked_grid(grid or CV_GRID, RoadParams, min_precision, what="cross-validation grid")
    items = load_manifest(folder)
    frames, skipped = [], []
    inners = []   # per frame, its obstacle_classes: the obstacles painted drivable
    for item in items:
        try:
            rgb = _load(item.image)
            road, valid, classes = labels_at_frame(item)
        except ScmrError as exc:
            skipped.append({"image": item.image.name, "error": str(exc)})
            continue
        frames.append((item, rgb, road, valid))
        inners.append(obstacle_classes(classes, valid))
    if not frames:
        raise InputError(f"{folder}: none of the {len(items)} manifest item(s) could be read")
    datasets = np.array([f[0].dataset for f in frames])
    names = sorted(set(datasets.tolist()))
    if len(names) < 2:
        raise InputError(f"{folder}: cross-validation needs at least two datasets, got {names}")
    keys = list(grid)
    combos = [dict(zip(keys, vals)) for vals in itertools.product(*grid.values())]
    params_list = [RoadParams(**combo).check() for combo in combos]
    # first, so a grid none of whose combinations could ship is refused before the long part
    syn = synthetic_scores(params_list, progress=progress) if synthetic else None
    allowed = syn["fits"] if syn is not None else None
    if allowed is not None and not allowed.any():
        below = "".join(f", {v} for {k}" for k, v in SYNTHETIC_KNOWN_BELOW.items())
        raise InputError(f"none of the grid's {len(combos)} combinations keeps the synthetic scenes at their floors "
                         f"(mean IoU >= {SYNTHETIC_IOU_TARGET} per kind{below}; precision >= {SYNTHETIC_PRECISION}), "
                         f"so no choice could ship; add --no-synthetic-floors to cross-validate without them")
    metrics = ("iou", "precision", "recall")
    scores = {m: np.zeros((len(combos), len(frames))) for m in metrics}
    green = [{c: np.zeros(len(combos), np.int64) for c in inn} for inn in inners]   # per frame and class
    for fi, (item, rgb, road, valid) in enumerate(frames):
        if progress:
            progress(fi, len(frames), item.image.name)
        for ci, (mask, _c, _a) in enumerate(best_masks(rgb, params_list)):
            s = score(mask, road, valid)
            for m in metrics:
                scores[m][ci, fi] = s[m]
            for c, g in obstacle_row(inners[fi], mask).items():
                green[fi][c][ci] = g[2]
    if progress:
        progress(len(frames), len(frames), "")
    half = np.array([score(bottom_half_mask(), road, valid)["iou"] for _i, _r, road, valid in frames])

    def choose(train: np.ndarray) -> int:
        return choose_combination(scores["iou"], scores["precision"], train, min_precision, allowed)

    best_all = choose(np.ones(len(frames), bool))
    cv = {m: np.zeros(len(frames)) for m in metrics}
    per = {}
    chosen = np.full(len(frames), best_all)   # each frame's fold's choice
    for d in names:
        held = datasets == d
        ci = choose(~held)
        chosen[held] = ci
        for m in metrics:
            cv[m][held] = scores[m][ci, held]
        per[d] = {
            "n": int(held.sum()),
            **{f"cv_{m}": float(scores[m][ci, held].mean()) for m in metrics},
            "cv_params": combos[ci],
            **{f"in_sample_{m}": float(scores[m][best_all, held].mean()) for m in metrics},
            "bottom_half_iou": float(half[held].mean()),
        }
    def obstacle_rows(pick: np.ndarray) -> list[dict]:
        return [{"dataset": str(datasets[fi]),
                 "obstacles": {c: [n, ni, int(green[fi][c][pick[fi]])] for c, (n, ni, _i) in inners[fi].items()}}
                for fi in range(len(frames))]

    keys_out = [f"cv_{m}" for m in metrics] + [f"in_sample_{m}" for m in metrics] + ["bottom_half_iou"]
    mean = {**{f"cv_{m}": float(cv[m].mean()) for m in metrics},
            **{f"in_sample_{m}": float(scores[m][best_all].mean()) for m in metrics},
            "bottom_half_iou": float(half.mean())}
    return {
        "grid": {k: list(v) for k, v in grid.items()},
        "combinations": len(combos),
        "min_precision": float(min_precision),
        "in_sample": {"params": combos[best_all], "mean_iou": float(scores["iou"][best_all].mean())},
        "per_dataset": per,
        "mean": mean,
        "mean_of_datasets": {k: float(np.mean([per[d][k] for d in names])) for k in keys_out},
        # the obstacles painted drivable under each frame's fold's choice and under the in-sample one
        "obstacles": {"cross-validated": obstacle_totals(obstacle_rows(chosen)),
                      "in-sample": obstacle_totals(obstacle_rows(np.full(len(frames), best_all)))},
        "skipped": skipped,
        "synthetic": {"checked": False} if syn is None else {
            "checked": True,
            "target": SYNTHETIC_IOU_TARGET,
            "floors": {k: synthetic_floor(k) for k in syn["iou"]},
            "precision": SYNTHETIC_PRECISION,
            "fit": int(allowed.sum()),
            # the in-sample choice's scores, per kind: what the shipped defaults give
            "in_sample": {k: {"iou": float(syn["iou"][k][best_all]), "precision": float(syn["precision"][k][best_all])}
                          for k in syn["iou"]},
        },
    }


def format_cv_table(result: dict) -> str:
    """A plain-text table of a :func:`cross_validate` result (IoU, precision, recall)."""
    lines = [f"{'dataset':12s} {'images':>6s} {'CV IoU':>7s} {'prec':>6s} {'recall':>6s} {'in-sample':>9s} "
             f"{'prec':>6s} {'recall':>6s} {'bottom half':>11s}  constants chosen on the other datasets"]

    def row(name: str, n: str, r: dict) -> str:
        return (f"{name[:12]:12s} {n:>6s} {r['cv_iou']:7.3f} {r['cv_precision']:6.3f} {r['cv_recall']:6.3f} "
                f"{r['in_sample_iou']:9.3f} {r['in_sample_precision']:6.3f} {r['in_sample_recall']:6.3f} "
                f"{r['bottom_half_iou']:11.3f}")

    for d, r in result["per_dataset"].items():
        chosen = ", ".join(f"{k}={v}" for k, v in r["cv_params"].items())
        lines.append(row(d, str(r["n"]), r) + "  " + chosen)
    n = sum(r["n"] for r in result["per_dataset"].values())
    lines.append(row("all (images)", str(n), result["mean"]))
    lines.append(row("all (datasets)", "", result["mean_of_datasets"]))
    chosen = ", ".join(f"{k}={v}" for k, v in result["in_sample"]["params"].items())
    lines.append(f"operating point: the highest IoU among combinations with mean precision >= "
                 f"{result.get('min_precision', 0):.2f} on the training images")
    syn = result.get("synthetic") or {}
    if syn.get("checked"):
        below = ", ".join(f"{k} {v:.2f}" for k, v in syn["floors"].items() if v < syn["target"])
        lines.append(f"  and, every choice, the synthetic scenes' floors: mean IoU >= {syn['target']:.2f} per kind"
                     f"{' (' + below + ')' if below else ''}, precision >= {syn['precision']:.2f}: "
                     f"{syn['fit']} of {result['combinations']} combinations meet them")
    else:
        lines.append("  (the synthetic scenes' floors not checked: --no-synthetic-floors)")
    lines.append(f"in-sample constants (chosen on all images, {result['combinations']} combinations): {chosen}")
    lines.extend(format_obstacles(result.get("obstacles", {})))
    return "\n".join(lines)


# ------------------------------------------------------------------ sequences (issue 27 item 2)
#: Frame rate of a sequence whose manifest items carry no ``fps`` (CamVid: 30 fps, and its file
#: names are frame indices, e.g. ``camvid_0016E5_01410`` is frame 1410 of drive 0016E5).
SEQUENCE_FPS = 30.0

#: The values :func:`cross_validate_sequences` chooses the carried model's constants from.
TRACK_GRID: dict[str, tuple] = {
    "forget": (0.5, 0.8),
    "agree": (0.3, 0.5),
    "patience": (2, 4),
    "max_gap_s": (0.0, 10.0),
    "extend": (False, True),
    "learn_shrunk": (False, True),
}

_SEQ_NAME = r"^(?P<seq>.+)_f?(?P<frame>\d+)$"


def sequences(items: list[Item], raw: list[dict] | None = None) -> dict[str, list[tuple[float, Item]]]:
    """Group manifest items into drives: ``{sequence: [(t seconds, item), ...]}`` in time order.

    An item belongs to a sequence through its manifest fields ``sequence`` and ``frame`` (and
    ``fps``, default :data:`SEQUENCE_FPS`) when ``raw`` (the manifest's item objects) gives them,
    else through its image name ``<dataset>_<sequence>_[f]<frame>`` (CamVid's naming:
    ``camvid_0016E5_01410``).  Only sequences of at least two frames are returned.
    """
    import re

    groups: dict[str, list[tuple[float, Item]]] = {}
    for i, item in enumerate(items):
        extra = raw[i] if raw is not None and i < len(raw) and isinstance(raw[i], dict) else {}
        stem = item.image.stem
        if "sequence" in extra and "frame" in extra:
            seq, frame = str(extra["sequence"]), extra["frame"]
        else:
            prefix = item.dataset + "_"
            m = re.match(_SEQ_NAME, stem[len(prefix):]) if stem.startswith(prefix) else None
            if m is None or "_" in m.group("seq"):
                continue
            seq, frame = m.group("seq"), m.group("frame")
        try:
            fps = float(extra.get("fps", SEQUENCE_FPS))
            t = float(frame) / fps
        except (TypeError, ValueError, ZeroDivisionError):
            raise ConfigError(f"{item.image.name}: bad frame/fps ({frame!r}, {extra.get('fps')!r})") from None
        groups.setdefault(f"{item.dataset}/{seq}", []).append((t, item))
    return {k: sorted(v, key=lambda r: r[0]) for k, v in sorted(groups.items()) if len(v) >= 2}


#: The box :func:`occluder` pastes over a 300x225 frame: rows 150-224, columns 95-204 (it covers the
#: bottom-centre cell, rows 188-224 and columns 100-199, and reaches the frame's bottom edge, as a
#: vehicle or a trunk close ahead does), in a flat dark red.
OCCLUDER = (slice(150, 225), slice(95, 205), (150, 40, 40))


def occluder_box(shape: tuple) -> np.ndarray:
    """Where :func:`occluder` pastes :data:`OCCLUDER` in a frame of ``shape`` (h, w): a bool mask."""
    box = np.zeros(shape[:2], bool)
    box[OCCLUDER[0], OCCLUDER[1]] = True
    return box


def occluder(rgb: np.ndarray, road: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 300x225 frame and its truth with :data:`OCCLUDER` pasted over the bottom-centre cell (copies)."""
    rows, cols, colour = OCCLUDER
    rgb, road = rgb.copy(), road.copy()
    rgb[rows, cols] = colour
    road[rows, cols] = False
    return rgb, road


def cross_validate_sequences(
    folder: str | Path,
    *,
    grid: dict[str, tuple] | None = None,
    min_precision: float = MIN_PRECISION,
    occlude: int = 0,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Leave-one-sequence-out cross-validation of the carried road model against the per-frame one.

    Each drive (:func:`sequences`) is run in time order from a cold track, once per combination of
    ``grid`` (default :data:`TRACK_GRID`); the per-frame model (``best``'s shipped constants) is
    scored on the same frames.  With ``occlude`` = k > 0, every k-th frame of a drive (the k-th,
    2k-th, ...) gets :func:`occluder` pasted over its bottom-centre cell, in the image and
    (as not road) in its truth: a stress test of the "seed is not road" failure (a vehicle
    close ahead).  For each sequence the combination with the highest mean IoU
    over the frames of the *other* sequences, among those with mean precision >= ``min_precision``
    there (all, when none is), is scored on it.  The model sees images only: labels are read
    for scoring and for choosing the constants on the other sequences.

    Returns
    -------
    dict
        ``{"grid", "combinations", "min_precision", "fps", "sequences": {name: {"n", "frames",
        "gaps_s", "per_frame": {iou, precision, recall}, "carried": {...}, "params",
        "carried_status": {status: count}, "images": [...]}}, "mean": {"per_frame", "carried"},
        "mean_of_sequences": {...}, "in_sample": {"params", "mean_iou"}, "skipped", "obstacles":
        {"per-frame": ..., "carried (CV)": ...}}`` (``obstacles``: :func:`obstacle_totals` per
        sequence, the carried model under each sequence's fold's choice; with ``occlude`` the
        pasted box is the class ``"occluder"`` and hides the classes under it; each image row
        carries its own as ``"per_frame_obstacles"`` and ``"carried_obstacles"``, ``{class:
        [labelled, inner, green]}``).
    """
    import itertools

    from scmr_mesh.imaging.codec import load_frame as _load
    from scmr_mesh.imaging.pipeline import DEFAULT_PARAMS, best_mask_from, working_frame
    from scmr_mesh.imaging.road_track import RoadTrack, TrackParams

    grid = _checked_grid(grid or TRACK_GRID, TrackParams, min_precision, what="sequence grid")
    items = load_manifest(folder)
    try:
        raw = json.loads((Path(folder) / "manifest.json").read_text())["items"]
    except (OSError, ValueError, KeyError, TypeError):
        raw = None
    seqs = sequences(items, raw)
    if len(seqs) < 2:
        raise InputError(f"{folder}: leave-one-sequence-out needs at least two sequences of two or more frames "
                         f"(named <dataset>_<sequence>_<frame>, or 'sequence' and 'frame' in the manifest); "
                         f"found {len(seqs)}")
    keys = list(grid)
    combos = [dict(zip(keys, vals)) for vals in itertools.product(*grid.values())]
    tparams = [TrackParams(**c).check() for c in combos]
    params = DEFAULT_PARAMS
    metrics = ("iou", "precision", "recall")
    runs, skipped = {}, []
    total = sum(len(v) for v in seqs.values())
    done = 0
    for name, frames in seqs.items():
        work, names, times = [], [], []
        inner: list[dict] = []   # per frame, its obstacle_classes
        for t, item in frames:
            if progress:
                progress(done, total, item.image.name)
            done += 1
            try:
                rgb = _load(item.image)
                road, valid, classes = labels_at_frame(item)
            except ScmrError as exc:
                skipped.append({"image": item.image.name, "error": str(exc)})
                continue
            if occlude and (len(work) + 1) % occlude == 0:
                rgb, road = occluder(rgb, road)
                box = occluder_box(road.shape)
                # what the box hides is not seen; the box itself is the obstacle ahead
                classes = {**{c: m & ~box for c, m in classes.items()}, "occluder": box}
            work.append((working_frame(rgb, params), road, valid))
            inner.append(obstacle_classes(classes, valid))
            names.append(item.image.name)
            times.append(t)
        if len(work) < 2:
            continue

        per_frame, pf_obstacles = [], []
        for fi, (w, r, v) in enumerate(work):
            mask = best_mask_from(w, params)[0]
            sc = score(mask, r, v)
            per_frame.append([sc[m] for m in metrics])
            pf_obstacles.append(obstacle_row(inner[fi], mask))
        per_frame = np.array(per_frame)
        carried = np.zeros((len(combos), len(work), len(metrics)))
        status, cv_obstacles = [], []
        for ci, tp in enumerate(tparams):
            track = RoadTrack()
            st, ob = [], []
            for fi, ((w, r, v), t) in enumerate(zip(work, times)):
                mask, _c, _a, how = best_mask_from(w, params, track=track, track_params=tp, t=t)
                sc = score(mask, r, v)
                carried[ci, fi] = [sc[m] for m in metrics]
                st.append(how)
                ob.append(obstacle_row(inner[fi], mask))
            status.append(st)
            cv_obstacles.append(ob)
        runs[name] = {"names": names, "times": times, "per_frame": per_frame, "carried": carried, "status": status,
                      "obstacles": (pf_obstacles, cv_obstacles)}
    if progress:
        progress(total, total, "")
    if len(runs) < 2:
        raise InputError(f"{folder}: fewer than two sequences could be read")

    def choose(train: list[str]) -> int:
        iou = np.concatenate([runs[n]["carried"][:, :, 0] for n in train], axis=1)
        prec = np.concatenate([runs[n]["carried"][:, :, 1] for n in train], axis=1)
        return choose_combination(iou, prec, np.ones(iou.shape[1], bool), min_precision)

    def means(a: np.ndarray) -> dict:
        return {m: float(a[:, i].mean()) for i, m in enumerate(metrics)}

    out_seq, all_pf, all_cv = {}, [], []
    ob_rows: dict[str, list[dict]] = {"per-frame": [], "carried (CV)": []}
    for name, run in runs.items():
        ci = choose([n for n in runs if n != name])
        pf_ob, cv_ob = run["obstacles"]
        ob_rows["per-frame"] += [{"dataset": name, "obstacles": o} for o in pf_ob]
        ob_rows["carried (CV)"] += [{"dataset": name, "obstacles": o} for o in cv_ob[ci]]
        counts: dict[str, int] = {}
        for how in run["status"][ci]:
            counts[how] = counts.get(how, 0) + 1
        gaps = np.diff(run["times"])
        out_seq[name] = {
            "n": len(run["names"]),
            "frames": run["names"],
            "gaps_s": {"min": float(gaps.min()), "median": float(np.median(gaps)), "max": float(gaps.max())},
            "per_frame": means(run["per_frame"]),
            "carried": means(run["carried"][ci]),
            "params": combos[ci],
            "carried_status": counts,
            "images": [{"image": n, "t_s": run["times"][fi], "carried_status": run["status"][ci][fi],
                        **{f"per_frame_{m}": float(run["per_frame"][fi, i]) for i, m in enumerate(metrics)},
                        **{f"carried_{m}": float(run["carried"][ci, fi, i]) for i, m in enumerate(metrics)},
                        "per_frame_obstacles": pf_ob[fi], "carried_obstacles": cv_ob[ci][fi]}
                       for fi, n in enumerate(run["names"])],
        }
        all_pf.append(run["per_frame"])
        all_cv.append(run["carried"][ci])
    best_all = choose(list(runs))
    return {
        "grid": {k: list(v) for k, v in grid.items()},
        "combinations": len(combos),
        "min_precision": float(min_precision),
        "occlude": int(occlude),
        "fps": SEQUENCE_FPS,
        "per_frame_params": params.as_dict(),
        "sequences": out_seq,
        "mean": {"per_frame": means(np.concatenate(all_pf)), "carried": means(np.concatenate(all_cv))},
        "mean_of_sequences": {k: {m: float(np.mean([out_seq[n][k][m] for n in out_seq])) for m in metrics}
                              for k in ("per_frame", "carried")},
        "in_sample": {"params": combos[best_all],
                      "mean_iou": float(np.concatenate([runs[n]["carried"][best_all, :, 0] for n in runs]).mean())},
        # per sequence and class, the obstacles painted drivable (they do not enter the choice)
        "obstacles": {k: obstacle_totals(r) for k, r in ob_rows.items()},
        "skipped": skipped,
    }


def format_sequences_table(result: dict) -> str:
    """A plain-text table of a :func:`cross_validate_sequences` result."""
    lines = [f"{'sequence':18s} {'frames':>6s} {'gap s (min/med/max)':>20s} {'per-frame IoU/prec/rec':>23s} "
             f"{'carried (CV) IoU/prec/rec':>26s}  what the track did; constants chosen on the other sequences"]

    def trio(r: dict) -> str:
        return f"{r['iou']:.3f}/{r['precision']:.3f}/{r['recall']:.3f}"

    for name, r in result["sequences"].items():
        g = r["gaps_s"]
        how = ", ".join(f"{k} {v}" for k, v in sorted(r["carried_status"].items()))
        chosen = ", ".join(f"{k}={v}" for k, v in r["params"].items())
        lines.append(f"{name[:18]:18s} {r['n']:6d} {g['min']:6.0f}/{g['median']:5.0f}/{g['max']:6.0f} "
                     f"{trio(r['per_frame']):>23s} {trio(r['carried']):>26s}  {how}; {chosen}")
    n = sum(r["n"] for r in result["sequences"].values())
    lines.append(f"{'all (frames)':18s} {n:6d} {'':20s} {trio(result['mean']['per_frame']):>23s} "
                 f"{trio(result['mean']['carried']):>26s}")
    lines.append(f"{'all (sequences)':18s} {'':6s} {'':20s} {trio(result['mean_of_sequences']['per_frame']):>23s} "
                 f"{trio(result['mean_of_sequences']['carried']):>26s}")
    chosen = ", ".join(f"{k}={v}" for k, v in result["in_sample"]["params"].items())
    if result.get("occlude"):
        lines.append(f"--occlude {result['occlude']}: every frame k * {result['occlude']} of each drive has a box pasted "
                     f"over its bottom-centre cell (a stress test, evaluate.OCCLUDER)")
    lines.append(f"operating point: the highest IoU among combinations with mean precision >= "
                 f"{result['min_precision']:.2f} on the training sequences; in-sample choice "
                 f"({result['combinations']} combinations): {chosen}")
    lines.extend(format_obstacles(result.get("obstacles", {}), group="sequence"))
    return "\n".join(lines)
