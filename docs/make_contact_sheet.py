"""Render docs/synthetic_speaker.png: the synthetic speaker's key postures, head-mounted view.

    python docs/make_contact_sheet.py [--seed 0] [--output docs/synthetic_speaker.png]

Postures: rest, /a/, /i/, /u/, bilabial closure (the corpus's /apa/) and a smile, each with
its name; a second row shows the desk view of the same postures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from articast.core.synthetic import RenderOptions, default_speaker, rest_pose  # noqa: E402
from articast.core.synthetic.corpus import corpus_controls  # noqa: E402
from articast.core.synthetic.sequence import default_camera  # noqa: E402


def postures(seed: int) -> list[tuple[str, np.ndarray]]:
    names, controls = corpus_controls(seed)
    pick = {n: controls[names.index(n)] for n in ("rest", "a", "i", "u", "apa")}
    smile = np.array([0.3, 0.8, 0.0, 0.0, 1.8, 0.0, 0.0])
    return [("rest", pick["rest"]), ("/a/", pick["a"]), ("/i/", pick["i"]), ("/u/", pick["u"]),
            ("bilabial /apa/", pick["apa"]), ("smile", smile)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--output", type=Path,
                    default=Path(__file__).resolve().parent / "synthetic_speaker.png")
    args = ap.parse_args()
    speaker = default_speaker(args.seed)
    rows = []
    for rig, scale in (("head", 0.5), ("desk", 0.5)):
        cam, pose = default_camera(rig), rest_pose(rig)
        tiles = []
        for label, c in postures(args.seed):
            img = speaker.render(c, pose, cam, RenderOptions(noise_sigma=2.0, seed=1))
            if rig == "desk":  # crop around the face
                img = img[40:360, 160:480]
                img = cv2.resize(img, (320, 320))[40:280]
            else:
                img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            cv2.putText(img, f"{label} ({rig})", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(img)
        rows.append(np.hstack(tiles[:3]))
        rows.append(np.hstack(tiles[3:]))
    sheet = np.vstack(rows)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.output), sheet):
        raise SystemExit(f"cannot write {args.output}")
    print(f"{sheet.shape[1]}x{sheet.shape[0]} -> {args.output}")


if __name__ == "__main__":
    main()
