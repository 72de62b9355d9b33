"""``articast export-fap``: a tracked sequence (JSON lines) -> an MPEG-4 ``.fap`` file.

Policy, as documented in ``--help``:

* frames whose ``quality.ok`` is false hold the last good frame's values (a player should see
  the face stay still, not jump to a guess); before the first good frame, the neutral face
  (alpha = 0, head at the reference pose) is held;
* the ``.fap`` frames are a uniform grid at ``--fps`` starting at the first record's time; each
  grid frame takes the latest record at or before its time (sample and hold), so dropped
  frames and jitter keep the timing right. By default fps is the track's real rate
  (:func:`track_fps`: 29.97 stays 29.97), and then every record is one ``.fap`` frame when the
  track is regular.
  A track without a time span (all time stamps equal) needs ``--fps`` and gives one ``.fap``
  frame per record.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-fap",
        help="convert a tracked sequence (JSON lines) to an MPEG-4 .fap file",
        description=(
            "Compute MPEG-4 FAPs (open_jaw, lip FAPs 3-18 and 51-60, head pitch/yaw/roll "
            "48-50) from the JSON lines written by 'articast track', and write the ASCII .fap "
            "file Xface, Greta, visage and VREng read. Frames with quality.ok false hold the "
            "last good values. Lower-lip FAPs are relative to open_jaw (use --absolute-lips "
            "for absolute ones); see docs/FAP_CHOICES.md. A track of an enrolled desk "
            "speaker also carries its eyes and brows: their FAPs (eyelids 19-22, eyeballs "
            "23-26, eyebrows 31-36) are written on the frames where they were seen "
            "(docs/UPPER_FACE.md)."
        ),
    )
    p.add_argument("track", type=Path, help="tracked sequence (.jsonl, one frame per line)")
    p.add_argument("--speaker", type=Path, help="speaker folder (from 'articast enroll') that "
                   "was tracked; or --model")
    p.add_argument("--model", type=Path, help="speaker model (.npz) that was "
                   "tracked; its feature-point labels define the FAPs")
    p.add_argument("-o", "--output", type=Path, required=True, help=".fap file to write")
    p.add_argument("--fps", type=float, help="frame rate of the .fap file (default: the "
                   "track's real rate from its time stamps, e.g. 29.97)")
    p.add_argument("--name", help="name in the .fap header (default: the output file name; "
                   "spaces become _)")
    p.add_argument("--head-reference", choices=("frontal", "first"), default="frontal",
                   help="pose with zero head FAPs: a frontal camera (default) or the first "
                   "good frame of the track")
    p.add_argument("--absolute-lips", action="store_true",
                   help="lower-lip FAPs absolute instead of relative to open_jaw")
    p.set_defaults(func=_export_fap)


def read_track(path: Path, param_names: tuple[str, ...]) -> list:
    """TrackResults of a JSON-lines file; blank lines are skipped, anything else must parse."""
    from articast.core.safe_io import read_regular_text
    from articast.core.tracking.result import TrackResult

    if not path.exists() and not path.is_symlink():
        raise InputError(f"{path}: no such file")
    text = read_regular_text(path)
    results = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            doc = json.loads(line)
            if not isinstance(doc, dict):
                raise ValueError("a line must hold one JSON object")
            unknown = set(doc.get("alpha", {})) - set(param_names)
            if unknown:
                raise ValueError(f"parameters {sorted(unknown)} are not in the model")
            _require_numbers(doc)
            result = TrackResult.from_dict(doc, param_names)
            if not np.all(np.isfinite(result.alpha)):
                raise ValueError("alpha values must be finite numbers")
            results.append(result)
        except RecursionError:
            raise InputError(f"{path}: line {n}: JSON nested too deeply") from None
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            reason = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise InputError(f"{path}: line {n}: not a track record: {reason}") from None
        if len(results) > 1 and results[-1].t < results[-2].t:
            raise InputError(f"{path}: line {n}: time stamp {results[-1].t} goes back in time")
    if not results:
        raise InputError(f"{path}: no frames")
    return results


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _require_numbers(doc: dict[str, Any]) -> None:
    """``t`` and the alpha values are JSON numbers: float() read "t": "0" (a string) as 0 s
    and the file passed (issue 39), so another tool's wrong types went unnoticed."""
    if "t" in doc and not _number(doc["t"]):
        raise ValueError(f"t must be a number of seconds, not {doc['t']!r:.40}")
    alpha = doc.get("alpha", {})
    if isinstance(alpha, dict):
        for name, v in alpha.items():
            if not _number(v):
                raise ValueError(f"alpha {name} must be a number, not {v!r:.40}")
    # the pose's numbers were read through float() too ("rotation": ["0", ...] passed), and
    # "ok": "false" was bool("false"), a good frame
    pose = doc.get("pose")
    if isinstance(pose, dict):
        for key in ("rotation", "translation"):
            v = pose.get(key)
            if isinstance(v, list) and not all(_number(x) for x in v):
                raise ValueError(f"pose {key} must be 3 numbers, not {str(v)[:40]}")
    quality = doc.get("quality", {})
    if not isinstance(quality, dict):
        raise ValueError(f"quality must be an object, not {quality!r:.40}")
    if "ok" in quality and not isinstance(quality["ok"], bool):
        raise ValueError(f"quality ok must be true or false, not {quality['ok']!r:.40}")
    for key in ("residual", "ms", "evals", "iterations"):
        if quality.get(key) is not None and not _number(quality[key]):
            raise ValueError(f"quality {key} must be a number, not {quality[key]!r:.40}")


def hold_last_good(
    alpha: np.ndarray, pose: np.ndarray, ok: np.ndarray, neutral_pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Replace frames with ``ok`` false by the last good frame (neutral before the first).

    alpha : (F, K); pose : (F, 6); ok : (F,) bool; neutral_pose : (6,).
    """
    good = np.where(ok, np.arange(len(ok)), -1)
    last = np.maximum.accumulate(good)
    alpha = np.where((last >= 0)[:, None], alpha[np.maximum(last, 0)], 0.0)
    pose = np.where((last >= 0)[:, None], pose[np.maximum(last, 0)], neutral_pose)
    return alpha, pose


def grid_indices(t: np.ndarray, fps: float) -> np.ndarray:
    """For a uniform grid at ``fps`` from ``t[0]`` to ``t[-1]``, the latest record index (G,)."""
    n = int(np.floor((t[-1] - t[0]) * fps + 0.5)) + 1
    grid = t[0] + np.arange(n) / fps
    tol = min(1e-3, 0.25 / fps)  # container time stamps are rounded to the millisecond
    return np.clip(np.searchsorted(t, grid + tol, side="right") - 1, 0, len(t) - 1)


STANDARD_RATES = tuple(sorted({float(n) for n in range(1, 241)}
                              | {n * 1000 / 1001 for n in (24, 30, 48, 60, 120, 240)}))
"""Rates a measured one snaps to: whole numbers and the NTSC family (23.976, 29.97, 59.94...)."""


def track_fps(t: np.ndarray) -> float:
    """The track's real frame rate (29.97 stays 29.97).

    The inverse of the mean time step over the steps within 25 % of the median one (gaps from
    dropped frames left out; the millisecond rounding of container time stamps averages away),
    snapped to the nearest of :data:`STANDARD_RATES` when within what 2 ms of time-stamp error
    over the track's span allows, else kept to 3 decimals. :class:`InputError` if no step.
    """
    dt = np.diff(t)
    dt = dt[dt > 0]
    if dt.size == 0:
        raise InputError("cannot infer fps from the time stamps (one frame, or all at the "
                         "same time): pass --fps")
    med = float(np.median(dt))
    steps = dt[np.abs(dt - med) <= 0.25 * med]
    fps = 1.0 / float(np.mean(steps))
    tolerance = fps * 0.002 / float(np.sum(steps)) + 1e-9
    nearest = min(STANDARD_RATES, key=lambda r: abs(r - fps))
    return nearest if abs(nearest - fps) <= tolerance else round(fps, 3)


MAX_FAP_FRAMES = 10_000_000
"""Frames of one .fap file (92 hours at 30 fps)."""


def fap_frame_count(results: list, where: str, fps: float | None = None) -> tuple[float, int]:
    """The rate and the number of frames of the .fap file for these track records; an
    :class:`InputError` for time stamps that give no usable rate or an absurd span (two
    records 1e9 s apart divided by zero before)."""
    t = np.array([r.t for r in results])
    if fps is None:
        try:
            fps = track_fps(t)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    if not (np.isfinite(fps) and 0.01 <= fps <= 10_000):
        raise InputError(f"{where}: a frame rate of {fps:.6g} fps from its time stamps is not "
                         "plausible: pass --fps")
    span = float(t[-1] - t[0])
    n = int(span * fps) + 1 if span > 0 else len(t)
    if n > MAX_FAP_FRAMES:
        raise InputError(f"{where}: its time stamps span {span:.6g} s, {n} frames at "
                         f"{fps:.6g} fps: over the limit of {MAX_FAP_FRAMES}")
    return fps, n


def _export_fap(args: argparse.Namespace) -> int:
    from articast.core.model.camera import FRONTAL
    from articast.core.model.face import FaceModel
    from articast.core.outputs.fap import FapEncoder, write_fap
    from articast.core.outputs.fap_io import fps_text

    if bool(args.speaker) == bool(args.model):
        raise InputError("give the tracked speaker: --speaker DIR or --model M (one of them)")
    model = FaceModel.load(args.model or args.speaker / "model.npz")
    results = read_track(args.track, model.param_names)
    alpha = np.array([r.alpha for r in results])
    pose = np.array([r.pose.as_vector() for r in results])
    ok = np.array([r.ok for r in results], dtype=bool)
    t = np.array([r.t for r in results])
    reference = FRONTAL
    if args.head_reference == "first":
        if not ok.any():
            raise InputError(f"{args.track}: no good frame to take as the head reference")
        reference = pose[int(np.argmax(ok)), :3]
    neutral_pose = np.concatenate([reference, pose[0, 3:]])
    alpha, pose = hold_last_good(alpha, pose, ok, neutral_pose)
    if args.fps is not None and not (np.isfinite(args.fps) and args.fps > 0):
        raise InputError(f"--fps must be a positive number, got {args.fps}")
    fps, _ = fap_frame_count(results, str(args.track), args.fps)
    # no usable time span (one record, or time stamps all equal): one .fap frame per record
    idx = grid_indices(t, fps) if t[-1] > t[0] else np.arange(len(t))
    encoder = FapEncoder(model, reference_rotation=reference, jaw_relative=not args.absolute_lips)
    values, mask = encoder.values(alpha[idx], pose[idx])
    uppers = [results[i].upper for i in idx]
    if any(u is not None for u in uppers):  # a track of this version: eyes and brows too
        from articast.core.outputs.upper import with_upper_faps

        values, mask = with_upper_faps(values, mask, uppers, encoder.fapu)
    write_fap(args.output, values, mask, fps, args.name)
    print(f"{len(idx)} frames at {fps_text(fps)} fps ({int((~ok).sum())} of {len(ok)} track frames "
          f"not ok, held) -> {args.output}")
    return 0
