"""``articast train-appearance`` and ``articast track``: offline tracking of a video."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import InputError
from articast.service.jsonsafe import dumps


def register(sub: argparse._SubParsersAction) -> None:
    tr = sub.add_parser(
        "train-appearance",
        help="train an appearance model from a video with known states",
        description=(
            "Fit an appearance model (Gaussian-derivative descriptors at automatically "
            "selected points, predicted from the articulatory parameters) by least "
            "squares on frames whose state is known. TRUTH is a JSON-lines file with one "
            "object per frame: frame, alpha {name: value}, pose {rotation, translation} — "
            "what 'articast synth sequence' writes and what 'articast track' produces."
        ),
    )
    tr.add_argument("video", type=Path,
                    help="enrolment video (any format OpenCV reads), frame i matching line i "
                    "of --truth")
    tr.add_argument("--truth", type=Path, required=True, help="states per frame (JSON lines)")
    tr.add_argument("--model", type=Path, required=True, help="speaker model (.npz)")
    tr.add_argument("--camera", type=Path, required=True, help="camera (.json)")
    tr.add_argument("-o", "--output", type=Path, required=True, help="appearance file (.npz)")
    tr.add_argument("--kind", default="la_quad",
                    choices=["la_cst", "la_lin", "la_quad", "tex_cst", "tex_lin"],
                    help="appearance model: la_lin is the paper's; la_quad (default) adds "
                         "quadratic terms and is measurably more accurate (README, Results)")
    tr.add_argument("--sigma", type=float, default=None,
                    help="filter scale in px (default: 0.7 mm on the face at the training "
                         "frames' depth, at least 1.25 px; 2.5 px on a head-mounted camera)")
    tr.add_argument("--per-param", type=int, default=12,
                    help="sample points per articulatory parameter (la; default 12)")
    tr.add_argument("--rig", choices=["head", "desk"], default="head",
                    help="how the camera moves relative to the head, as 'track --rig': "
                         "head (default: a head-mounted camera) or desk (free head motion). "
                         "The point selection plans for the head pose the tracker will "
                         "estimate, and on a desk la models also learn how the face's "
                         "shading changes as the head turns")
    tr.add_argument("--selection", default="auto",
                    choices=["auto", "information", "displacement"],
                    help="la point selection: 'information' picks the points that best "
                         "constrain the articulation in the training frames (expected RMS "
                         "3D error), 'displacement' is the paper's rule (largest motion per "
                         "parameter); auto (default) = information with >= 2(K+1) frames")
    tr.add_argument("--frames", type=int, default=0, help="use only the first N frames")
    tr.set_defaults(func=_train)

    tk = sub.add_parser(
        "track",
        help="track a video offline, one JSON line per frame",
        description=(
            "Track the speaker's articulatory parameters and head pose in every frame of a "
            "video. Output: one JSON object per line (frame, t, alpha by name, pose, quality), "
            "flushed as it goes. With --speaker (a folder from 'articast enroll') nothing else "
            "is needed: the face finder starts the tracker, checks every few frames that the "
            "face is there, and restarts it after a loss; the articulation and head pose "
            "written are then smoothed with the frames after each one (the motion model's "
            "fixed-lag smoother and the One Euro filter run both ways: steadier lips than "
            "live, without the live filter's lag) and averaged with a second tracker that "
            "reads the finding landmarks on every frame (two readers' errors; ~15-20 ms of "
            "CPU a frame more: --single-reader for one), unless --causal. With "
            "--model/--appearance/--camera (a bead-lab speaker), the first frame starts from "
            "--init-pose, or from the first state of --init-truth, or else from a search "
            "around a frontal face --distance-mm in front of the camera. A frame that cannot "
            "be tracked says so: quality.ok false and a reason starting with blank, no_face, "
            "diverged, occluded or left_image."
        ),
    )
    tk.add_argument("video", type=Path, help="the video to track")
    tk.add_argument("--speaker", type=Path,
                    help="speaker folder from 'articast enroll' (replaces --model, "
                         "--appearance, --camera)")
    tk.add_argument("--model", type=Path, help="speaker model (.npz), without --speaker")
    tk.add_argument("--appearance", type=Path,
                    help="appearance model (.npz, 'articast train-appearance'), without --speaker")
    tk.add_argument("--camera", type=Path,
                    help="camera (.json); with --speaker it replaces the enrolment's camera")
    tk.add_argument("-o", "--output", type=Path, required=True,
                    help="track file (.jsonl; written only if tracking succeeds)")
    tk.add_argument("--overlay", type=Path, metavar="VIDEO.mp4",
                    help="also write the video with the fit drawn on every frame: the mesh "
                         "thin and translucent (green ok, red not), the lip contours on top "
                         "(outer yellow, inner magenta), a desk speaker's tracked eyelids "
                         "(cyan), irises (blue) and brows (orange). H.264 in MP4, which "
                         "browsers play (VP9 for a .webm name)")
    tk.add_argument("--overlay-zoom", choices=["auto", "on", "off"], default="auto",
                    help="with --overlay: a magnified inset of the face in a corner: auto "
                         "(default) when the face spans under 25 %% of the frame's height "
                         "(a phone clip), on, or off")
    add_span_arguments(tk)
    tk.add_argument("--optimiser", default="gauss-newton", choices=["gauss-newton", "nelder-mead"],
                    help="gauss-newton (default, analytic Jacobians) or the paper's simplex")
    tk.add_argument("--rig", choices=["head", "desk"],
                    help="head: camera fixed to the head (pose barely moves); desk: free head "
                         "(default: the speaker's enrolment rig, else head)")
    tk.add_argument("--init-pose", help="rx,ry,rz,tx,ty,tz (axis-angle rad, mm)")
    tk.add_argument("--init-truth", type=Path, help="take the first frame's pose from this file")
    tk.add_argument("--distance-mm", type=float, default=300.0,
                    help="face distance for the initial search (default 300)")
    tk.add_argument("--causal", action="store_true",
                    help="with --speaker: write each frame's estimate as the live service "
                         "streams it (from that frame and the ones before only), instead of "
                         "smoothed with the frames after (docs/TRACKING.md, 'Offline')")
    tk.add_argument("--single-reader", action="store_true",
                    help="with --speaker, offline: track with the live reader (FaceMesh v1) "
                         "alone, instead of averaging it with a second tracker that reads the "
                         "finding landmarks (FaceLandmarker v2) on every frame, which costs "
                         "~15-20 ms of CPU a frame more (docs/TRACKING.md, 'Offline')")
    tk.add_argument("--readers", type=int, choices=(1, 2), default=1,
                    help="with --speaker --causal: 2 streams each frame as the live service "
                         "does with --readers 2 (the mean of a FaceMesh v1 and a "
                         "FaceLandmarker v2 reader's trackers, ~3x the CPU; docs/RESULTS.md, "
                         "'Two readers live'); offline tracking reads two already")
    tk.add_argument("--quiet", action="store_true", help="no progress line")
    tk.set_defaults(func=_track)


def add_span_arguments(p: argparse.ArgumentParser) -> None:
    """--start/--end: a part of the clip, without cutting it with other tools."""
    from articast.service.video import SPAN_HELP

    p.add_argument("--start", metavar="WHEN",
                   help=f"begin at this point of the clip: {SPAN_HELP}; default the start")
    p.add_argument("--end", metavar="WHEN",
                   help=f"stop before this point: {SPAN_HELP}; default the end")


def load_states(path: Path, param_names: tuple[str, ...]) -> list:
    """TrackResults of a truth/track JSON-lines file, with line numbers in errors."""
    from articast.core.tracking.result import TrackResult
    from articast.service.video import read_jsonl

    out = []
    for n, obj in enumerate(read_jsonl(path), 1):
        try:
            out.append(TrackResult.from_dict(obj, param_names))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: record {n}: missing or malformed field ({exc})") from None
    if not out:
        raise InputError(f"{path}: no records (an empty JSON-lines file)")
    return out


def _train(args: argparse.Namespace) -> int:
    from articast.core.appearance.models import TrainingFrame, train_appearance
    from articast.core.model.camera import Camera
    from articast.core.model.face import FaceModel
    from articast.core.tracking.tracker import appearance_options
    from articast.service.progress import Progress
    from articast.service.video import iter_video

    model = FaceModel.load(args.model)
    camera = Camera.load(args.camera)
    states = {s.frame: s for s in load_states(args.truth, model.param_names)}
    frames = []
    for i, _, img in iter_video(args.video):
        if args.frames and i >= args.frames:
            break
        if i in states:
            frames.append(TrainingFrame(img, states[i].alpha, states[i].pose))
    if not frames:
        raise InputError(f"{args.truth}: no state matches a frame of {args.video}")
    _check_size(frames[0].image, camera)
    prog = Progress(1, "training")
    app = train_appearance(model, camera, frames, args.kind, sigma=args.sigma,
                           per_param=args.per_param, selection=args.selection,
                           **appearance_options(args.rig, args.kind))
    prog.update()
    prog.close()
    app.save(args.output)
    print(f"{args.kind}: {app.n_samples} sample points, {len(frames)} frames, variance "
          f"explained {', '.join(f'{e:.1%}' for e in app.explained)} -> {args.output}")
    return 0


def _check_size(image: np.ndarray, camera) -> None:
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"video frames are {w}x{h} but the camera is calibrated for "
                         f"{camera.width}x{camera.height}")


def _initial_pose(args: argparse.Namespace, param_names):
    from articast.core.model.camera import Pose

    if args.init_pose:
        try:
            v = [float(x) for x in args.init_pose.split(",")]
        except ValueError:
            v = []
        if len(v) != 6:
            raise InputError("--init-pose needs 6 numbers: rx,ry,rz,tx,ty,tz")
        return Pose(np.asarray(v[:3]), np.asarray(v[3:]))
    if args.init_truth:
        states = load_states(args.init_truth, param_names)
        if not states:
            raise InputError(f"{args.init_truth}: empty")
        return states[0].pose
    return Pose(translation=np.array([0.0, 0.0, args.distance_mm]))


def _frame_size(video: Path) -> tuple[int, int]:
    """(width, height) of the video's frames (one clear error if it cannot be read)."""
    from articast.service.video import iter_video

    for _, _, img in iter_video(video):
        return img.shape[1], img.shape[0]
    raise InputError(f"{video}: no frame")  # pragma: no cover - iter_video raises first


def _sized(camera, size: tuple[int, int], quiet: bool):
    """The camera fitted to the video's frame size, saying so when it was scaled."""
    from articast.service.processors import fit_camera, scaling_note

    note = scaling_note(camera, *size)
    camera = fit_camera(camera, *size, what="the video's frames")
    if note and not quiet:
        print(f"articast track: {note}", file=sys.stderr)
    return camera


def _make_tracker(args: argparse.Namespace, size: tuple[int, int]):
    """(tracker with .track(image, t), model, camera) for --speaker or the bead-lab files,
    the camera fitted to the video's frame ``size``."""
    from articast.core.tracking.tracker import Tracker, TrackingPolicy

    if args.speaker:
        if args.model or args.appearance or args.init_pose or args.init_truth:
            raise InputError("--speaker replaces --model, --appearance and the --init options")
        from articast.core.faces.finder import FaceFinder
        from articast.core.faces.live import LiveTracker, live_policy
        from articast.core.faces.scheme import mediapipe_scheme
        from articast.core.faces.speaker import Speaker

        speaker = Speaker.load(args.speaker)
        if args.camera:
            from dataclasses import replace

            from articast.core.model.camera import Camera

            speaker = replace(speaker, camera=Camera.load(args.camera))
        from dataclasses import replace as _replace

        speaker = _replace(speaker, camera=_sized(speaker.camera, size, args.quiet))
        rig = args.rig or speaker.rig
        policy = live_policy(rig, optimiser=args.optimiser)
        live = LiveTracker(speaker, FaceFinder.load(), mediapipe_scheme(speaker.rig),
                           tracking=policy, clock=time.perf_counter)
        if args.readers == 2:
            from articast.core.faces.two_readers import TwoReaderTracker

            try:
                return (TwoReaderTracker.of(live, tracking=policy), speaker.model,
                        speaker.camera)
            except ValueError as exc:
                raise InputError(f"--readers 2: {exc}") from None
        return live, speaker.model, speaker.camera
    if not (args.model and args.appearance and args.camera):
        raise InputError("give --speaker DIR (from 'articast enroll'), or all of --model, "
                         "--appearance and --camera")
    from articast.core.appearance.models import AppearanceModel
    from articast.core.model.camera import Camera
    from articast.core.model.face import FaceModel

    model = FaceModel.load(args.model)
    app = AppearanceModel.load(args.appearance, model)
    camera = _sized(Camera.load(args.camera), size, args.quiet)
    rig = args.rig or "head"
    policy = TrackingPolicy.for_rig(rig, optimiser=args.optimiser)
    if args.optimiser == "nelder-mead":
        policy = TrackingPolicy.for_rig(rig, optimiser=args.optimiser, levels=(0,))
    tracker = Tracker(model, app, camera, policy,
                      _initial_pose(args, model.param_names), clock=time.perf_counter)
    return tracker, model, camera


def _track(args: argparse.Namespace) -> int:
    import os
    import tempfile

    from articast.service.progress import Progress
    from articast.service.video import Span, iter_video, video_frame_count

    if args.output.is_dir():
        raise InputError(f"-o {args.output}: is a folder, expected a file name (.jsonl)")
    if args.single_reader and (args.causal or not args.speaker):
        raise InputError("--single-reader is for offline tracking with --speaker (without "
                         "--causal, which reads one network as the live service does)")
    if args.readers != 1 and not (args.causal and args.speaker):
        raise InputError(f"--readers {args.readers} is for --speaker with --causal (offline "
                         "tracking reads two readers already; --single-reader for one)")
    span = Span(args.start, args.end)
    tracker, model, camera = _make_tracker(args, _frame_size(args.video))
    smoother = second = second_smoother = None
    if getattr(tracker, "fusion", None) is not None and not args.causal:  # fused LiveTracker
        from articast.core.faces.offline import OfflineSmoother, reader_ratio_of

        if not args.single_reader:
            second = _second_tracker(args, tracker)
        readers = 1 if second is None else 2
        smoother = OfflineSmoother.for_live(tracker, readers)
        if second is not None:
            second_smoother = OfflineSmoother.for_live(second, readers)
    contours, upper = _contours(args)
    total = video_frame_count(args.video)
    if span:
        total = span.frames(total, _fps(args.video))
    prog = Progress(total, "tracking", quiet=args.quiet)
    identity = None
    if args.speaker:  # one line, said above the progress bar, never a refusal
        from articast.service.identity import IdentityWarning

        identity = IdentityWarning(tracker.speaker, lambda text: prog.say(
            f"articast track: {text}"), f"--speaker {args.speaker}")
    n_ok = n = 0
    ms = []
    reasons: dict[str, int] = {}
    folder = args.output.resolve().parent
    if not folder.is_dir():
        raise InputError(f"-o {args.output}: the folder {folder} does not exist")
    # written beside the output and renamed at the end: a failed track leaves no file
    fd, tmp_name = tempfile.mkstemp(prefix=f".{args.output.name}.", suffix=".part", dir=folder)
    tmp = Path(tmp_name)
    video = drawing = None
    # each tracker's reader's lip gap per frame, for the offline opening
    ratios: tuple[list[float], list[float]] = ([], [])
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            for i, t, img in iter_video(args.video, span):
                if n == 0 and args.overlay:
                    from articast.service.overlay import Overlay, VideoOut

                    video = VideoOut(args.overlay, _fps(args.video),
                                     (img.shape[1], img.shape[0]))
                    drawing = Overlay(video, model, camera, contours, upper,
                                      args.overlay_zoom)
                res = tracker.track(img, t)
                if identity is not None:
                    identity.see(tracker)
                out.write(dumps(res.to_dict(model.param_names)) + "\n")
                out.flush()
                if smoother is not None:
                    smoother.add(res)
                    ratios[0].append(reader_ratio_of(res))
                spent = res.ms
                if second is not None and second_smoother is not None:
                    again = second.track(img, t)
                    second_smoother.add(again)
                    ratios[1].append(reader_ratio_of(again))
                    spent += again.ms  # (the frame's cost is both readers')
                if drawing is not None:
                    drawing.write(img, res)
                n += 1
                n_ok += res.ok
                ms.append(spent)
                if not res.ok:
                    code = res.reason.split(":", 1)[0]
                    reasons[code] = reasons.get(code, 0) + 1
                prog.update(note="" if res.ok else f"frame {i}: {res.reason[:40]}")
        prog.close()
        if smoother is not None:
            if not args.quiet and n > 0:
                both = (" and averaging the two readers' trackers (--single-reader: FaceMesh "
                        "v1's alone; " if second_smoother is not None else " (")
                print(f"articast track: smoothing {n} frames with the frames after each"
                      f"{both}--causal: as streamed live)", file=sys.stderr, flush=True)
            from articast.core.faces.offline import averaged, with_reader_gap

            frames = smoother.finish()
            if second_smoother is not None:
                frames = averaged(frames, second_smoother.finish())
            # the opening half the readers' own lip gap, as live (core/faces/offline.py)
            frames = with_reader_gap(frames, [np.array(r) for r in ratios if r],
                                     model, camera)
            _rewrite_smoothed(tmp, frames, model)
        why = "".join(f", {k} {v}" for k, v in sorted(reasons.items()))
        if n_ok == 0:  # exit 0 would pass a useless track off as a result; and as --help
            # says, -o is written only when tracking succeeds (issue 39: a clip without the
            # face left a file of ok=false lines a script would take for a track)
            hint = ("is the enrolled speaker in view?" if args.speaker else "check the camera, "
                    "model and appearance files, and --init-pose")
            raise InputError(f"{args.video}: none of its {n} frames could be tracked "
                             f"({why.lstrip(', ')}; {hint}); {args.output} not written")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 is for the part file only
        os.replace(tmp, args.output)  # every frame read: the lines say what happened
    finally:
        prog.close()
        if video is not None:
            video.close()
            if tmp.exists() and args.overlay.exists():  # an error: no half overlay either
                args.overlay.unlink()
        tmp.unlink(missing_ok=True)
    print(f"{n} frames tracked ({n_ok} ok{why}), median {np.median(ms):.2f} ms/frame "
          f"-> {args.output}" + (f", overlay {args.overlay}" if args.overlay else ""))
    return 0


def _second_tracker(args: argparse.Namespace, first):
    """Offline track's second tracker (core/faces/offline.py, ``second_reader``): the finding
    landmarks read on every frame through the speaker's model; None for a speaker enrolled
    without their observation model."""
    import time

    from articast.core.faces.live import LiveTracker, live_policy
    from articast.core.faces.offline import SECOND_READER, second_reader
    from articast.core.faces.scheme import mediapipe_scheme

    speaker = second_reader(first.speaker)
    if speaker is None:
        if not args.quiet and first.speaker.points is not None:  # (a head rig has neither)
            print("articast track: one reader (the speaker was enrolled without the finding "
                  "landmarks' observation model: enrol again to read both)", file=sys.stderr,
                  flush=True)
        return None
    rig = args.rig or speaker.rig
    # the first tracker's finder (detector and FaceLandmarker v2) finds and reads for it
    # too: the same networks, not loaded twice more; its reading crops as the policy's
    # reader does (FusionPolicy.reader_keep_roi), as a LiveTracker's own reader would
    assert SECOND_READER.fusion is not None
    reader = first.finder.with_policy(SECOND_READER.fusion.reader_policy())
    return LiveTracker(speaker, first.finder, mediapipe_scheme(speaker.rig), SECOND_READER,
                       tracking=live_policy(rig, optimiser=args.optimiser),
                       clock=time.perf_counter, reader=reader)


def _rewrite_smoothed(path: Path, frames: list, model) -> None:
    """The track file's lines (each frame's live estimate, written as it went) rewritten with
    the smoothed articulation, lips and head pose (core/faces/offline.py)."""
    import json
    import os

    from articast.core.outputs.lips import lips_dict

    part = path.with_name(path.name + ".smoothed")
    try:
        with open(path, encoding="utf-8") as src, open(part, "w", encoding="utf-8") as dst:
            for line, frame in zip(src, frames, strict=True):
                if frame is not None:
                    d = json.loads(line)
                    d["alpha"] = {n: float(v) for n, v in
                                  zip(model.param_names, frame.alpha, strict=True)}
                    d["pose"] = frame.pose.to_dict()
                    d["lips"] = lips_dict(model, frame.alpha)
                    line = dumps(d) + "\n"
                dst.write(line)
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)


def _fps(video: Path) -> float:
    import cv2

    from articast.service.video import open_capture

    cap = open_capture(str(video))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()


def _contours(args: argparse.Namespace) -> tuple[list, Any]:
    """The overlay's lip contours and eyes-and-brows layout (an enrolled speaker's)."""
    if not args.overlay:
        return [], None
    if args.overlay.is_dir():
        raise InputError(f"--overlay {args.overlay}: is a folder, expected a file name (.mp4)")
    if not args.speaker:
        return [], None
    from articast.core.faces.speaker import Speaker
    from articast.service.overlay import lip_contours, upper_layout

    speaker = Speaker.load(args.speaker)
    return lip_contours(speaker), upper_layout(speaker)
