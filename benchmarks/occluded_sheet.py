"""One picture of every clip's ``occluded`` frames: the first row of each clip's grid
(``peers.py --grid DIR`` writes DIR/CLIP_occluded.jpg, every flagged frame with its fitted
mesh), titled with the clip and how many rows it has in all.

    python benchmarks/occluded_sheet.py RUN/final_grid RUN/final_grid_f -o RUN/occluded.jpg
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

TILE = 160  # peers.write_occluded_grid's tile
TITLE = 22


def sheet(grids: list[Path]) -> np.ndarray | None:
    """The rows, one per clip with flagged frames (None: no clip has any)."""
    rows = []
    for folder in grids:
        for path in sorted(folder.glob("*_occluded.jpg")):
            img = cv2.imread(str(path))
            if img is None:
                continue
            n_rows = max(1, img.shape[0] // TILE)
            title = np.zeros((TITLE, img.shape[1], 3), np.uint8)
            name = path.name[: -len("_occluded.jpg")]
            cv2.putText(title, f"{name}: first row of its flagged frames ({n_rows} rows in all)",
                        (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                        cv2.LINE_AA)
            rows.append(np.vstack([title, img[:TILE]]))
    if not rows:
        return None
    width = max(r.shape[1] for r in rows)
    return np.vstack([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("grids", nargs="+", type=Path, help="peers.py --grid folders")
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args()
    img = sheet(args.grids)
    if img is None:
        raise SystemExit("no occluded frames in these grids")
    cv2.imwrite(str(args.output), img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    print(f"{args.output}: {img.shape[1]}x{img.shape[0]}")


if __name__ == "__main__":
    main()
