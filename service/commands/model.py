"""``articast build-model`` and ``articast calibrate``."""

from __future__ import annotations

import argparse
from pathlib import Path

from articast.service.jsonsafe import dumps


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "build-model",
        help="build a speaker model from a posture corpus (guided iterative PCA)",
        description=(
            "Build the 7-parameter linear articulatory model (jaw1 lips1 lips2 lips3 lips4 jaw2 "
            "lar1) from a posture corpus by guided iterative PCA, and print the variance each "
            "parameter explains (like Table 1 of the paper). The corpus format is described in "
            "the README; 'articast synth corpus' writes one for the built-in speaker."
        ),
    )
    p.add_argument("corpus", type=Path, help="posture corpus (.npz)")
    p.add_argument("-o", "--output", type=Path, required=True, help="model file to write (.npz)")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.set_defaults(func=_build_model)

    c = sub.add_parser(
        "calibrate",
        help="calibrate a camera from chessboard images",
        description="Estimate intrinsics and distortion from chessboard views; writes camera JSON.",
    )
    c.add_argument("images", type=Path, nargs="+", help="image files, or one folder of them")
    c.add_argument("-o", "--output", type=Path, required=True, help="camera file to write (.json)")
    c.add_argument("--pattern", default="9x6", help="inner corners, COLSxROWS (default 9x6)")
    c.add_argument("--square-mm", type=float, default=25.0, help="square side in mm (default 25)")
    c.set_defaults(func=_calibrate)


def _build_model(args: argparse.Namespace) -> int:
    from articast.core.model.build import Corpus, build_model

    corpus = Corpus.load(args.corpus)
    model, table = build_model(corpus)
    model.save(args.output)
    if args.json:
        print(dumps(table.to_json(), indent=2))
    else:
        print(f"model of {corpus.postures.shape[1]} points from {corpus.postures.shape[0]} "
              f"postures -> {args.output}\n")
        print(table.format())
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    import cv2

    from articast.core.errors import InputError
    from articast.core.model.camera import calibrate_chessboard

    try:
        cols, rows = (int(v) for v in args.pattern.lower().split("x"))
    except ValueError:
        raise InputError(f"--pattern must look like 9x6, got {args.pattern!r}") from None
    paths: list[Path] = []
    for p in args.images:
        paths.extend(sorted(q for q in p.iterdir() if q.is_file()) if p.is_dir() else [p])
    images = []
    from articast.core.safe_io import require_regular

    for p in paths:
        require_regular(p)  # a FIFO would block OpenCV for ever
        im = cv2.imread(str(p))
        if im is None:
            raise InputError(f"{p}: not a readable image")
        images.append(im)
    cal = calibrate_chessboard(images, (cols, rows), args.square_mm)
    cal.camera.save(args.output)
    print(f"calibrated from {cal.images_used} images ({cal.images_rejected} without the "
          f"pattern): RMS reprojection error {cal.rms_px:.3f} px -> {args.output}")
    return 0
