"""Scoring drivable masks against labelled images (``scmr eval``).

The data folder holds a ``manifest.json`` in the ``scmr-roads-manifest/1``
format (see ``../shared/data/roads/manifest.json``): a list of items with
``image``, ``mask``, ``dataset``, ``mask_mode`` (``"gray"`` or ``"rgb"``, RGB
colours in RGB order), ``road`` (values that are road) and ``ignore``
(values left out of scoring).  Every image is scored at 300x225: the
prediction is made at that size and the ground truth is resized with
nearest-neighbour interpolation.
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
        out.append(
            Item(
                image=folder / str(it["image"]),
                mask=folder / str(it["mask"]),
                dataset=str(it.get("dataset", "default")),
                mask_mode=mode,
                road=road,
                ignore=ignore,
            )
        )
    return out


def _values(vals, mode: str) -> tuple:
    if not isinstance(vals, list):
        raise TypeError(f"expected a list, got {type(vals).__name__}")
    if mode == "gray":
        return tuple(int(v) for v in vals)
    out = []
    for v in vals:
        if not (isinstance(v, list) and len(v) == 3):
            raise ValueError(f"rgb values must be [R, G, B] lists, got {v!r}")
        out.append(tuple(int(c) for c in v))
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
    m = _read_mask(item)
    m = cv2.resize(m, (FRAME_WIDTH, FRAME_HEIGHT), interpolation=cv2.INTER_NEAREST)
    if item.mask_mode == "gray":
        road = np.isin(m, item.road)
        ignore = np.isin(m, item.ignore) if item.ignore else np.zeros(m.shape, bool)
    else:
        road = np.zeros(m.shape[:2], bool)
        ignore = np.zeros(m.shape[:2], bool)
        for c in item.road:
            road |= np.all(m == np.array(c, np.uint8), axis=2)
        for c in item.ignore:
            ignore |= np.all(m == np.array(c, np.uint8), axis=2)
    return road, ~ignore


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
        also carries its ``per_dataset`` means.
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
            road, valid = truth_at_frame(item)
        except ScmrError as exc:  # one unreadable pair must not sink the whole evaluation
            skipped.append({"image": item.image.name, "error": str(exc)})
            continue
        res = segment_drivable(rgb, mode=mode)
        rows.append({"image": item.image.name, "dataset": item.dataset, **score(res.mask, road, valid)})
        for o in others:
            pred = bottom_half_mask() if o == "bottom_half" else segment_drivable(rgb, mode=o).mask
            base_rows[o].append({"image": item.image.name, "dataset": item.dataset, **score(pred, road, valid)})
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
    }
    return out


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
    return "\n".join(lines)


#: The values :func:`cross_validate` chooses ``best``'s constants from (every combination).
CV_GRID: dict[str, tuple] = {
    # SRM Q 4096 and sunlit 120 were in the grid until issue 27 and no fold of the 60-image
    # cross-validation chose them; they left to make room for the abstention's constants
    "q": (2048.0,),
    "p": (0.9, 0.95, 0.99),
    "frac": (0.3, 0.5),
    "gap": (10, 20),
    "shade": (0.0, 0.2),
    "sunlit": (80.0,),
    "opening": (0, 9),
    "reach": (0.0, 0.35),
    "cap": (0.4, 0.5),
    "standing": (False, True),
}

#: The operating point: cross-validation chooses, among the combinations whose mean precision on
#: the training images is at least this, the one with the highest mean IoU there (issue 27: a
#: robot drives where the mask is green, so green where it cannot drive is the costly error).
#: The target is 0.85 on held-out data; precision on the training images overstates it, hence
#: the margin.  0.88 was picked after comparing 0.85 / 0.88 / 0.90 on the cross-validation
#: itself (docs/ACCURACY.md gives all three), so its cross-validated figures are a little optimistic.
MIN_PRECISION = 0.88


def cross_validate(
    folder: str | Path,
    *,
    grid: dict[str, tuple] | None = None,
    min_precision: float = MIN_PRECISION,
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

    Returns
    -------
    dict
        ``{"grid", "combinations", "in_sample": {"params", "mean_iou"},
        "per_dataset": {d: {"n", "cv_iou", "cv_precision", "cv_recall", "cv_params",
        "in_sample_iou", "in_sample_precision", "in_sample_recall", "bottom_half_iou"}},
        "mean": {...same keys...}, "mean_of_datasets": {...}, "min_precision", "skipped"}``;
        means are over images (each image weighs the same) and over datasets.
    """
    import itertools

    from scmr_mesh.imaging.codec import load_frame as _load
    from scmr_mesh.imaging.pipeline import best_masks
    from scmr_mesh.imaging.road_model import RoadParams

    grid = dict(grid or CV_GRID)
    if not 0 <= min_precision <= 1:
        raise InputError(f"min_precision must be in [0, 1], got {min_precision}")
    fields = set(RoadParams.__dataclass_fields__)
    for k, vals in grid.items():
        if k not in fields:
            raise InputError(f"cross-validation grid: unknown constant {k!r}; choose from {', '.join(sorted(fields))}")
        if not vals:
            raise InputError(f"cross-validation grid: no values for {k!r}")
    items = load_manifest(folder)
    frames, skipped = [], []
    for item in items:
        try:
            frames.append((item, _load(item.image), *truth_at_frame(item)))
        except ScmrError as exc:
            skipped.append({"image": item.image.name, "error": str(exc)})
    if not frames:
        raise InputError(f"{folder}: none of the {len(items)} manifest item(s) could be read")
    datasets = np.array([f[0].dataset for f in frames])
    names = sorted(set(datasets.tolist()))
    if len(names) < 2:
        raise InputError(f"{folder}: cross-validation needs at least two datasets, got {names}")
    keys = list(grid)
    combos = [dict(zip(keys, vals)) for vals in itertools.product(*grid.values())]
    params_list = [RoadParams(**combo).check() for combo in combos]
    metrics = ("iou", "precision", "recall")
    scores = {m: np.zeros((len(combos), len(frames))) for m in metrics}
    for fi, (item, rgb, road, valid) in enumerate(frames):
        if progress:
            progress(fi, len(frames), item.image.name)
        for ci, (mask, _c, _a) in enumerate(best_masks(rgb, params_list)):
            s = score(mask, road, valid)
            for m in metrics:
                scores[m][ci, fi] = s[m]
    if progress:
        progress(len(frames), len(frames), "")
    half = np.array([score(bottom_half_mask(), road, valid)["iou"] for _i, _r, road, valid in frames])

    def choose(train: np.ndarray) -> int:
        iou = scores["iou"][:, train].mean(axis=1)
        ok = scores["precision"][:, train].mean(axis=1) >= min_precision
        if ok.any():
            iou = np.where(ok, iou, -1.0)
        return int(np.argmax(iou))

    best_all = choose(np.ones(len(frames), bool))
    cv = {m: np.zeros(len(frames)) for m in metrics}
    per = {}
    for d in names:
        held = datasets == d
        ci = choose(~held)
        for m in metrics:
            cv[m][held] = scores[m][ci, held]
        per[d] = {
            "n": int(held.sum()),
            **{f"cv_{m}": float(scores[m][ci, held].mean()) for m in metrics},
            "cv_params": combos[ci],
            **{f"in_sample_{m}": float(scores[m][best_all, held].mean()) for m in metrics},
            "bottom_half_iou": float(half[held].mean()),
        }
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
        "skipped": skipped,
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
    lines.append(f"in-sample constants (chosen on all images, {result['combinations']} combinations): {chosen}")
    return "\n".join(lines)
