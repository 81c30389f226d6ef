"""Sub-commands of the imaging area: ``scmr segment`` and ``scmr eval``.

Heavy imports (numpy, OpenCV, numba) happen inside the handlers so that
``scmr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scmr_mesh import cliargs as ca

MODES = ("best", "thesis")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``segment`` and ``eval`` to ``scmr``."""
    p = sub.add_parser(
        "segment",
        help="drivable-region masks, red/green maps and overlays for images",
        description=(
            "Run the drivable-region pipeline (SPEC section 1) on images and write, per input, "
            "<stem>.mask.png (255 = drivable), <stem>.rg.png (green = drivable, red = not) and "
            "<stem>.overlay.png, all at 300x225.  With --stages also <stem>.srm.png (SRM region "
            "means), <stem>.otsu.png (Otsu black/white), <stem>.hist.png (bottom-centre histogram, "
            "threshold T marked) and <stem>.edges.png (Sobel magnitude).  A bad input prints one "
            "line on stderr; the others are still processed and the exit status is 1."
        ),
    )
    p.add_argument("images", nargs="*", metavar="IMAGE", help="PNG or JPEG files")
    p.add_argument(
        "--synthetic",
        action="append",
        default=[],
        metavar="KIND[:SEED]",
        help="also segment a built-in synthetic scene (structured_road, dirt_road, tunnel, hallway, "
        "desert), e.g. tunnel:3; repeatable",
    )
    p.add_argument("--out", required=True, type=ca.PathArg("out-dir", as_path=True), metavar="DIR", help="output folder (created if missing)")
    p.add_argument("--mode", choices=MODES, default="best", help="best (default, most accurate) or thesis (the dissertation's rules)")
    p.add_argument("--stages", action="store_true", help="also write the intermediate images")
    p.add_argument("--q", type=ca.positive("SRM complexity", hi=1e6, example="32"), default=32.0, help="SRM complexity Q (default: %(default)s; best mode runs SRM at 16 x Q)")
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser(
        "eval",
        help="score the pipeline against labelled images (IoU, F1, precision, recall)",
        description=(
            "Score the pipeline on a folder holding manifest.json (format of shared/data/roads). "
            "Every image is scored at 300x225 (masks resized with nearest neighbour; 'ignore' "
            "pixels left out), against the baselines 'bottom half is road' and the thesis mode.  "
            "Where the masks label obstacles (people, cyclists, vehicles, poles: CamVid, RELLIS-3D, "
            "UMich, or a manifest's 'obstacles' field) the table ends with how much of them each mask "
            "paints drivable (with --cv under the folds' and the in-sample choices, with --sequences per "
            "drive for the per-frame and the carried model).  Prints a table and writes JSON."
        ),
    )
    p.add_argument("folder", type=ca.PathArg("in-dir", as_path=True, what="a folder with manifest.json, images/ and masks/", example="../shared/data/roads"), metavar="DIR", help="folder with manifest.json, images/ and masks/")
    p.add_argument("--mode", choices=MODES, default="best", help="mode to score (default: %(default)s)")
    p.add_argument("--cv", action="store_true",
                   help="leave-one-dataset-out cross-validation of best's constants: for each dataset, choose "
                        "them on the other datasets and score this one; prints cross-validated and in-sample "
                        "IoU, precision and recall and the bottom-half baseline per dataset; every choice is made "
                        "among the combinations that keep the synthetic scenes at their floors, as the shipped "
                        "defaults must (about 30 s on the shared images, 2 cores)")
    p.add_argument("--sequences", action="store_true",
                   help="the road model carried across a robot's frames against the per-frame one: group the "
                        "labelled frames into drives (<dataset>_<sequence>_<frame> names, CamVid's, at 30 fps; or "
                        "'sequence'/'frame'/'fps' in the manifest), run each in time order from a cold track, "
                        "leave-one-sequence-out cross-validation of the track's constants; prints IoU, precision "
                        "and recall per sequence for both (about 20 s on the shared images, 2 cores)")
    p.add_argument("--occlude", type=ca.Number(lo=0, hi=1000, integer=True, what="frame period", example="3"), default=0,
                   metavar="K", help="with --sequences, a stress test: paste a box over the bottom-centre cell of every "
                                     "K-th frame of each drive (image and truth; the seed is then not road; the obstacle table counts "
                                     "the box as the class 'occluder'); 0 = off")
    p.add_argument("--min-precision", type=ca.Number(lo=0, hi=1, what="precision", example="0.88"), default=None, metavar="P",
                   help="with --cv or --sequences, the operating point: choose the best IoU among the combinations "
                        "whose mean precision on the training images is at least P (default 0.88; 0 = IoU alone)")
    p.add_argument("--no-synthetic-floors", dest="synthetic_floors", action="store_false",
                   help="with --cv, let the choices ignore the synthetic scenes' floors (the table's last lines "
                        "print them; scmr_mesh.imaging.evaluate.SYNTHETIC_*): the protocol before 2026-11-28, under "
                        "which a fold could choose constants that could not be shipped")
    p.add_argument("--json", type=ca.PathArg("out-file", as_path=True), metavar="FILE", help="write the full result as JSON here")
    p.set_defaults(func=cmd_eval)



# ------------------------------------------------------------------ segment
def _parse_synthetic(spec: str) -> tuple[str, int]:
    from scmr_mesh.errors import InputError
    from scmr_mesh.imaging.synthetic import SCENE_KINDS

    kind, _, seed = spec.partition(":")
    if kind not in SCENE_KINDS:
        raise InputError(f"--synthetic {spec!r}: unknown kind {kind!r}; choose one of {', '.join(SCENE_KINDS)}")
    try:
        return kind, int(seed) if seed else 0
    except ValueError:
        raise InputError(f"--synthetic {spec!r}: the seed must be an integer, got {seed!r}") from None


def hist_image(hist, threshold: int, *, width: int = 512, height: int = 240):
    """Draw a 256-bin histogram with the threshold marked: (height, width, 3) uint8 RGB."""
    import cv2
    import numpy as np

    img = np.full((height, width, 3), 255, np.uint8)
    h = np.asarray(hist, np.float64)
    top = h.max() if h.max() > 0 else 1.0
    bw = width / 256.0
    base = height - 20
    for v in range(256):
        if h[v] > 0:
            y = int(round(base - (base - 10) * h[v] / top))
            cv2.rectangle(img, (int(v * bw), y), (max(int((v + 1) * bw) - 1, int(v * bw)), base), (60, 60, 60), -1)
    x = int((threshold + 0.5) * bw)
    cv2.line(img, (x, 0), (x, base), (220, 0, 0), 1)
    cv2.putText(img, f"T={threshold}", (min(x + 4, width - 60), 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (220, 0, 0), 1)
    cv2.line(img, (0, base), (width - 1, base), (0, 0, 0), 1)
    for v in (0, 64, 128, 192, 255):
        cv2.putText(img, str(v), (int(v * bw), height - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    return img


def _write(path: Path, array) -> None:
    from scmr_mesh.errors import InputError
    from scmr_mesh.imaging.codec import encode_png

    try:
        path.write_bytes(encode_png(array))
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from None


def segment_one(rgb, stem: str, out: Path, *, mode: str, stages: bool, q: float = 32.0) -> list[Path]:
    """Segment one frame and write its pictures; return the paths written."""
    import numpy as np

    from scmr_mesh.imaging.pipeline import segment_drivable
    from scmr_mesh.imaging.steps import overlay, red_green

    res = segment_drivable(rgb, mode=mode, q=q, stages=True)
    st = res.stages
    files = {
        "mask": res.mask,
        "rg": red_green(res.mask),
        "overlay": overlay(st["frame"], res.mask),
    }
    if stages:
        edges = st["edges"]
        files["srm"] = st["srm"]
        files["otsu"] = st["otsu"]
        files["hist"] = hist_image(st["histogram"], res.threshold)
        files["edges"] = np.clip(edges / 4.0, 0, 255).astype(np.uint8)
    written = []
    for name, arr in files.items():
        p = out / f"{stem}.{name}.png"
        _write(p, arr)
        written.append(p)
    return written


def cmd_segment(args: argparse.Namespace) -> int:
    from scmr_mesh.errors import InputError, ScmrError

    if not args.images and not args.synthetic:
        raise InputError("no input: give IMAGE files and/or --synthetic KIND[:SEED]")
    if args.out.exists() and not args.out.is_dir():
        raise InputError(f"--out must be a folder, got the file {args.out}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create --out folder {args.out}: {exc.strerror or exc}") from None
    synthetic = [_parse_synthetic(s) for s in args.synthetic]

    from scmr_mesh.imaging.codec import load_frame
    from scmr_mesh.imaging.synthetic import make_scene

    jobs: list[tuple[str, object]] = [(str(p), p) for p in args.images]
    jobs += [(f"{k}:{s}", (k, s)) for k, s in synthetic]
    failed = 0
    used: set[str] = set()
    for i, (label, src) in enumerate(jobs, 1):
        print(f"[{i}/{len(jobs)}] {label}", file=sys.stderr)
        try:
            if isinstance(src, tuple):
                rgb, _ = make_scene(src[0], seed=src[1])
                stem = f"{src[0]}_{src[1]}"
            else:
                rgb = load_frame(src)
                stem = Path(src).stem
            base, n = stem, 2
            while stem in used:  # two inputs with the same name
                stem, n = f"{base}-{n}", n + 1
            used.add(stem)
            segment_one(rgb, stem, args.out, mode=args.mode, stages=args.stages, q=args.q)
        except ScmrError as exc:
            failed += 1
            print(f"scmr: error: {exc}", file=sys.stderr)
    ok = len(jobs) - failed
    print(f"wrote {ok} of {len(jobs)} input(s) to {args.out}", file=sys.stderr)
    return 1 if failed else 0


# --------------------------------------------------------------------- eval
def cmd_eval(args: argparse.Namespace) -> int:
    from scmr_mesh.errors import InputError
    from scmr_mesh.imaging.evaluate import cross_validate, evaluate, format_cv_table, format_table

    def progress(i: int, n: int, name: str) -> None:
        if name:
            print(f"[{i + 1}/{n}] {name}", file=sys.stderr)

    if args.cv and args.sequences:
        raise InputError("--cv and --sequences are two evaluations; give one of them")
    if not args.synthetic_floors and not args.cv:
        raise InputError("--no-synthetic-floors applies to --cv only (how its folds choose best's constants)")
    if args.sequences:
        if args.mode != "best":
            raise InputError(f"--sequences evaluates best's carried road model; thesis has none (got --mode {args.mode})")
        from scmr_mesh.imaging.evaluate import MIN_PRECISION, cross_validate_sequences, format_sequences_table

        mp = MIN_PRECISION if args.min_precision is None else args.min_precision
        result = cross_validate_sequences(args.folder, min_precision=mp, occlude=int(args.occlude), progress=progress)
        return _report_cv(args, result, format_sequences_table(result))
    if args.occlude:
        raise InputError("--occlude is a stress test of --sequences; add --sequences")
    if args.min_precision is not None and not args.cv:
        raise InputError("--min-precision is the operating point of --cv or --sequences; add one of them")
    if args.cv:
        if args.mode != "best":
            raise InputError(f"--cv cross-validates the constants of best; thesis has none to choose (got --mode {args.mode})")
        from scmr_mesh.imaging.evaluate import MIN_PRECISION

        mp = MIN_PRECISION if args.min_precision is None else args.min_precision
        result = cross_validate(args.folder, min_precision=mp, synthetic=args.synthetic_floors, progress=progress)
        return _report_cv(args, result, format_cv_table(result))

    result = evaluate(args.folder, mode=args.mode, progress=progress)
    print(format_table(result))
    if args.json:
        _write_json(args.json, result)
    for s in result["skipped"]:
        print(f"scmr: error: skipped {s['image']}: {s['error']}", file=sys.stderr)
    if result["skipped"]:
        print(f"{len(result['skipped'])} item(s) skipped; the means cover the {len(result['images'])} scored",
              file=sys.stderr)
    return 1 if result["skipped"] else 0


def _report_cv(args: argparse.Namespace, result: dict, table: str) -> int:
    """Print a cross-validation's table, write its JSON, name the images it skipped (exit 1 if any)."""
    print(table)
    if args.json:
        _write_json(args.json, result)
    for s in result["skipped"]:
        print(f"scmr: error: skipped {s['image']}: {s['error']}", file=sys.stderr)
    return 1 if result["skipped"] else 0


def _write_json(path: Path, doc: dict) -> None:
    from scmr_mesh.errors import InputError

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from None
    print(f"wrote {path}", file=sys.stderr)


