"""Does the delegate look like the speaker? Per real clip: enrol on the first part (as
benchmarks/real_clips.py does), build the delegate from the enrolment part's frames tracked
live, then track the held-out rest live and draw the delegate at each tracked state from the
real camera; its face-region SSIM against the real frame (core/delegate/texture.py
``face_ssim``), for the full texture (tex lin: T0 + sum alpha_k T_k) and for the mean texture
alone (T0, the baseline), on held-out frames the tracker marks ok; and the same in the mouth
region (the box around the tracked outer lips grown by half their size each way), where
the articulation-dependent texture acts.

    python tools/fetch_real_clips.py        # once
    python benchmarks/delegate_clips.py --json [--pictures docs/delegate] [--clips cap13]
        [--speakers DIR]

Pictures: per clip, three held-out frames as rows of (real frame, delegate at the tracked
state, their absolute difference x3), cropped to the face.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_clips import CLIPS, SIZE, enrol_speaker, read_frames, track_live  # noqa: E402

from articast.core.delegate.build import build_delegate, tracked_frames  # noqa: E402
from articast.core.delegate.texture import face_ssim, render  # noqa: E402
from articast.core.faces.finder import FaceFinder  # noqa: E402
from articast.core.faces.speaker import Speaker  # noqa: E402
from articast.core.model.camera import Camera  # noqa: E402

CLIP_DIR = Path.home() / ".cache" / "articast" / "clips"
EVAL_FRAMES = 60
"""Held-out frames measured per clip (evenly spread over the ok ones)."""


def run_clip(name: str, pictures: Path | None, speakers: Path | None = None) -> dict:
    frames, fps = read_frames(CLIP_DIR / f"{name}.mp4")
    enrol_s, test_s = CLIPS[name]
    n_enrol = int(enrol_s * fps)
    enrol, held = frames[:n_enrol], frames[n_enrol:n_enrol + int(test_s * fps)]
    camera = Camera.default(*SIZE, 60.0)
    t0 = time.perf_counter()
    folder = speakers / name if speakers is not None else None
    if folder is not None and (folder / "speaker.json").is_file():
        speaker = Speaker.load(folder)  # enrolled before on the same frames (--speakers)
    else:
        speaker = enrol_speaker(enrol, fps, camera=camera)
        if folder is not None:
            speaker.save(folder)
    enrol_s_taken = time.perf_counter() - t0
    finder = FaceFinder.load(threads=1)
    t0 = time.perf_counter()
    states = tracked_frames(speaker, enrol, finder, times=np.arange(len(enrol)) / fps)
    delegate = build_delegate(speaker.model, camera, states)
    build_s = time.perf_counter() - t0
    results, _, _ = track_live(speaker, held, fps)
    ok = [i for i, r in enumerate(results) if r.ok]
    pick = [ok[i] for i in np.linspace(0, len(ok) - 1, min(EVAL_FRAMES, len(ok))).round()
            .astype(int)]
    lin, cst, rows, mouth_lin, mouth_cst = [], [], [], [], []
    mean_tex = delegate.texture
    for n, i in enumerate(pick):
        r = results[i]
        drawn, mask = render(delegate.mesh, delegate.texture_at(r.alpha), r.alpha, r.pose, camera)
        base, mask0 = render(delegate.mesh, mean_tex, r.alpha, r.pose, camera)
        lin.append(face_ssim(held[i], drawn, mask))
        cst.append(face_ssim(held[i], base, mask0))
        box = _mouth_box(speaker, r, camera)
        mouth_lin.append(face_ssim(held[i], drawn, mask & box))
        mouth_cst.append(face_ssim(held[i], base, mask0 & box))
        if pictures is not None and n in (len(pick) // 6, len(pick) // 2, 5 * len(pick) // 6):
            rows.append(_row(held[i], drawn, mask))
    if pictures is not None and rows:
        pictures.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(pictures / f"{name}.jpg"), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 88])
    return {"clip": name, "enrol_frames_textured": len(states),
            "held_out_frames": len(held), "held_out_ok": len(ok), "measured": len(pick),
            "ssim_tex_lin": {"mean": round(float(np.nanmean(lin)), 4),
                             "p10": round(float(np.nanpercentile(lin, 10)), 4)},
            "ssim_mean_texture": {"mean": round(float(np.nanmean(cst)), 4),
                                  "p10": round(float(np.nanpercentile(cst, 10)), 4)},
            "mouth_ssim_tex_lin": round(float(np.nanmean(mouth_lin)), 4),
            "mouth_ssim_mean_texture": round(float(np.nanmean(mouth_cst)), 4),
            "texels_seen_pct": delegate.report["texels_seen_pct"],
            "enrol_s": round(enrol_s_taken, 1), "delegate_build_s": round(build_s, 1)}


def _mouth_box(speaker, res, camera: Camera) -> np.ndarray:
    """The image box around the tracked outer lips, grown by half their size each way."""
    m = speaker.model
    lips = camera.project_head(m.shape(res.alpha)[m.group("lip_outer")], res.pose)
    lo, hi = lips.min(0), lips.max(0)
    grow = 0.5 * (hi - lo)
    (x0, y0), (x1, y1) = np.floor(lo - grow).astype(int), np.ceil(hi + grow).astype(int)
    box = np.zeros((camera.height, camera.width), bool)
    box[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
    return box


def _row(real: np.ndarray, drawn: np.ndarray, mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    r0, r1 = max(rows.min() - 10, 0), min(rows.max() + 10, real.shape[0])
    c0, c1 = max(cols.min() - 10, 0), min(cols.max() + 10, real.shape[1])
    comp = np.where(mask[..., None], drawn, real)
    diff = np.clip(np.abs(real.astype(np.int16) - comp.astype(np.int16)) * 3, 0, 255
                   ).astype(np.uint8)
    tiles = [x[r0:r1, c0:c1] for x in (real, comp, diff)]
    h, w = 240, 200
    return np.hstack([cv2.resize(t, (w, h), interpolation=cv2.INTER_AREA) for t in tiles])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", nargs="*", default=list(CLIPS))
    ap.add_argument("--pictures", type=Path)
    ap.add_argument("--speakers", type=Path,
                    help="keep each clip's enrolled speaker here and reuse it when present")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out = [run_clip(c, args.pictures, args.speakers) for c in args.clips]
    print(json.dumps(out, indent=1) if args.json else out)


if __name__ == "__main__":
    main()
