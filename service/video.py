"""Reading recorded videos and ground-truth/track JSON-lines files (offline commands)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import InputError


def iter_video(path: str | os.PathLike[str]) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield ``(index, t_seconds, bgr_image)`` for every frame of a video file.

    Time stamps come from the container (falling back to index / fps). Raises
    :class:`InputError` if the file is missing or no frame can be decoded.
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such video file")
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise InputError(f"{p}: cannot open as a video (unknown or corrupt container)")
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    i = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            t = ms / 1000.0 if ms > 0 or i == 0 else (i / fps if fps > 0 else float(i))
            if i > 0 and fps > 0 and ms <= 0:
                t = i / fps
            yield i, t, frame
            i += 1
    finally:
        cap.release()
    if i == 0:
        raise InputError(f"{p}: no frame could be decoded (corrupt or empty video)")


def video_frame_count(path: str | os.PathLike[str]) -> int:
    """Frame count the container declares (0 if unknown)."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        return max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    finally:
        cap.release()


def read_jsonl(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Objects of a JSON-lines file; a malformed line is an InputError naming its number."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    out = []
    with open(p, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as exc:
                raise InputError(f"{p}:{n}: not valid JSON ({exc.msg})") from None
            if not isinstance(obj, dict):
                raise InputError(f"{p}:{n}: each line must be a JSON object")
            out.append(obj)
    return out
