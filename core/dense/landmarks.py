"""Landmark files of a scan: the 68 points of the iBUG scheme in 3-D (menpo's ``.ljson``, the
iBUG ``.pts`` format, or a JSON list), in the scan's own frame and unit
(:mod:`articast.core.dense.scan` aligns the scan by them)."""

from __future__ import annotations

import json
import os

import numpy as np

from articast.core.errors import InputError

N_IBUG = 68

_LJSON_GROUPS = (  # iBUG order: (names a .ljson may give the group, first index, size)
    (("jaw", "chin"), 0, 17),
    (("left_eyebrow", "leyebrow"), 17, 5),
    (("right_eyebrow", "reyebrow"), 22, 5),
    (("nose",), 27, 9),
    (("left_eye", "leye"), 36, 6),
    (("right_eye", "reye"), 42, 6),
    (("mouth",), 48, 20),
)


def parse_landmarks(text: str, kind: str, source: str = "<landmarks>") -> np.ndarray:
    """(68, 3) float64 iBUG-68 landmarks, scan frame and unit; NaN rows for missing points.

    kind : ``"ljson"`` (menpo v2/v3; points listed by labelled group are put into iBUG
    order, e.g. menpo3d's ``james.ljson``, which lists the eyes before the brows),
    ``"pts"`` (``version: 1`` / ``n_points: 68`` / ``{ x y z ... }``) or ``"json"`` (a list
    of 68 [x, y, z], or ``{"points": [...]}``). :class:`InputError` naming ``source``.
    """
    try:
        if kind == "pts":
            pts = _parse_pts(text)
        else:
            doc = json.loads(text)
            pts = _parse_ljson(doc) if kind == "ljson" else _points(
                doc["points"] if isinstance(doc, dict) and "points" in doc else doc)
    except (ValueError, KeyError, TypeError, IndexError, AttributeError, StopIteration,
            RecursionError) as exc:
        raise InputError(f"{source}: not a {kind} landmark file ({exc!r})") from None
    if pts.shape != (N_IBUG, 3):
        raise InputError(f"{source}: need the {N_IBUG} points of the iBUG scheme in 3-D, got "
                         f"{pts.shape[0]} points of {pts.shape[1] if pts.ndim == 2 else 0} "
                         "coordinates")
    if np.isinf(pts).any():
        raise InputError(f"{source}: landmark coordinates must be finite")
    # what an alignment can use: coordinates of a scan's size (1e308 squared is inf), and
    # three given points that span a plane (all missing, or all at one place, was accepted)
    given = pts[~np.isnan(pts).any(axis=1)]
    if np.abs(given).max(initial=0.0) > 1e6:
        raise InputError(f"{source}: landmark coordinates beyond 1e6: not a face scan's")
    spread = (np.linalg.svd(given - given.mean(axis=0), compute_uv=False)
              if len(given) >= 3 else np.zeros(2))
    if spread[1] <= 1e-9 * max(1.0, float(spread[0])):
        raise InputError(f"{source}: the given landmarks ({len(given)} of {N_IBUG}) do not "
                         "span a plane (fewer than 3, all at one place, or on one line)")
    return pts


def _points(rows: object) -> np.ndarray:
    if not isinstance(rows, list):
        raise ValueError("expected a list of points")
    out = [[np.nan] * 3 if r is None or (isinstance(r, list) and None in r) else r
           for r in rows]
    arr = np.array(out, dtype=np.float64)
    return arr.reshape(len(out), -1) if arr.size else np.zeros((0, 3))


def _parse_ljson(doc: dict) -> np.ndarray:
    if "groups" in doc and isinstance(doc["groups"], dict):  # v3: the first (usually only) group
        group = next(iter(doc["groups"].values()))
        pts, labels = _points(group["landmarks"]["points"]), group.get("labels", [])
    else:  # v2
        pts, labels = _points(doc["landmarks"]["points"]), doc.get("labels", [])
    masks = {str(lab["label"]).lower(): list(lab["mask"]) for lab in labels}
    if len(pts) != N_IBUG or not masks:
        return pts
    out = np.full((N_IBUG, 3), np.nan)
    for names, first, size in _LJSON_GROUPS:
        mask = next((masks[n] for n in names if n in masks), None)
        if mask is None or len(mask) != size:
            return pts  # labels of another scheme: take the listed order
        out[first:first + size] = pts[mask]
    return out


def _parse_pts(text: str) -> np.ndarray:
    body = text.split("{", 1)[1].rsplit("}", 1)[0] if "{" in text else text
    rows = [line.split() for line in body.splitlines() if line.strip()]
    if any(len(r) != 3 for r in rows):
        raise ValueError("each point needs 3 coordinates (x y z)")
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def load_landmarks(path: str | os.PathLike[str]) -> np.ndarray:
    """:func:`parse_landmarks` of a file, the format from its suffix (.ljson, .pts, .json)."""
    from articast.core.safe_io import read_regular_bytes

    suffix = os.fspath(path).rsplit(".", 1)[-1].lower()
    if suffix not in ("ljson", "pts", "json"):
        raise InputError(f"{path}: landmarks must be .ljson, .pts or .json (iBUG 68 points)")
    text = read_regular_bytes(path).decode("utf-8", errors="replace")
    return parse_landmarks(text, suffix, str(path))
