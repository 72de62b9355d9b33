"""``articast enroll``: a speaker folder from a short clip of the person reading aloud."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import ArticastError, InputError
from articast.service.jsonsafe import dumps

MIN_SECONDS = 20.0
MIN_APERTURE_RANGE_MM = 8.0
MIN_WIDTH_RANGE_MM = 5.0
DEFAULT_FOV_DEG = 60.0


def register(sub: argparse._SubParsersAction) -> None:
    en = sub.add_parser(
        "enroll",
        help="enrol a real speaker from a 20-60 s clip of them reading aloud",
        description=(
            "Build a speaker folder (face model, appearance, camera, enrolment statistics) "
            "from a video of one person reading aloud in front of any webcam: face landmarks "
            "per frame (bundled MediaPipe models on onnxruntime), head pose removed, the "
            "guided PCA of the paper on the landmarks (jaw1 lips1 lips2 lips3 lips4 jaw2; "
            "lar1, the throat, is not visible to a camera and stays 0), scale in mm from an "
            "assumed inter-pupillary distance (or mouth width when the eyes are not seen), "
            "local appearance trained at the landmark states and refined by "
            "analysis-by-synthesis. Read with open vowels, rounded and spread lips "
            "(e.g. 'a', 'ee', 'oo', 'p', 'f') so every parameter is covered, and blink "
            "naturally: on a desk camera the same clip gives the speaker's own open eye, "
            "closed eye and neutral brows, which the tracked eyelids, gaze and brows are "
            "measured against (docs/UPPER_FACE.md; a warning when it holds no blink). Then: "
            "'articast track VIDEO --speaker DIR' or 'articast serve --source me=... "
            "--speaker DIR'."
        ),
    )
    en.add_argument("video", type=Path, help="the enrolment clip (any format FFmpeg reads)")
    en.add_argument("-o", "--output", type=Path, required=True,
                    help="speaker folder to write (created; files in it are replaced)")
    en.add_argument("--camera", type=Path,
                    help="camera calibration (.json, 'articast calibrate'); default: an "
                         f"undistorted camera with a {DEFAULT_FOV_DEG:g} deg horizontal field "
                         "of view at the clip's frame size (a typical webcam)")
    en.add_argument("--rig", choices=["desk", "head"], default="desk",
                    help="desk: a webcam in front of the speaker, free head (default); head: "
                         "a head-mounted camera that sees the face from the nose down")
    en.add_argument("--ipd-mm", type=float, default=63.0,
                    help="inter-pupillary distance assumed for the scale in mm (desk; adult "
                         "mean 63, default)")
    en.add_argument("--mouth-width-mm", type=float, default=50.0,
                    help="mouth width at rest assumed for the scale in mm when the eyes are not "
                         "seen (head rig; default 50)")
    en.add_argument("--depth", choices=["rigid", "landmarks"], default="rigid",
                    help="each frame's depth: rigid (default) the head's, posed on the pixels "
                         "of the nose and upper face; landmarks: the landmark model's own "
                         "per-point guess")
    en.add_argument("--flow", action=argparse.BooleanOptionalAction, default=None,
                    help="refine the landmarks' pixels by optical flow, frame to frame, pulled "
                         "back to the landmarks (default: on with --rig head, where it helped "
                         "the rendered face's lips; off on a desk camera, where it did not "
                         "help the real clips)")
    en.add_argument("--kind", default="la_quad", choices=["la_lin", "la_quad"],
                    help="appearance model (default la_quad: la_lin plus squared terms)")
    en.add_argument("--max-frames", type=int, default=600,
                    help="analyse at most this many frames, evenly spread (default 600; a longer "
                         "clip adds 100 consecutive frames from its middle for the motion model)")
    en.add_argument("--name", default="", help="speaker name (default: the clip's name)")
    from articast.service.commands.track import add_span_arguments

    add_span_arguments(en)
    en.add_argument("--delegate", action=argparse.BooleanOptionalAction, default=True,
                    help="also write the speaker's textured 3D face (delegate.npz, from the "
                         "clip's frames; 'articast delegate' rebuilds it): what a browser "
                         "avatar and 'articast export-gltf' show of them (default on; "
                         "--no-delegate keeps no picture of the face in the folder)")
    en.add_argument("--json", action="store_true", help="print the report as JSON")
    en.add_argument("--quiet", action="store_true", help="no progress line")
    en.set_defaults(func=_enroll)


def find_faces(video: Path, max_frames: int, quiet: bool = False, span=None,
               read: bool = True, total: int | None = None, progress=None):
    """Frames (strided to at most ``max_frames``, plus a run of consecutive frames from the
    middle of a long clip: the motion model learns from frame-to-frame motion,
    :func:`~articast.core.tracking.kalman.process_noise`), their landmarks (F, 478, 3), found
    (F,), the clip's duration (s), frame size, the number of frames read (of ``span``, a
    :class:`~articast.service.video.Span`, when given), the live reader's landmarks of the
    same frames (F, 468, 3; None unless ``read``) and when each frame was taken (F,) s.

    ``total``: the clip's frame count when the caller counted it (a browser's WebM declares
    none: every frame would be analysed); ``progress(stage, done, of)``: told as the frames
    are read (the room's enrolment shows it)."""
    import cv2

    from articast.core.faces.build import analysed_frames
    from articast.core.faces.finder import FaceFinder, read_every_frame
    from articast.core.faces.live import reader_finder
    from articast.service.progress import Progress
    from articast.service.video import iter_video, open_capture, video_frame_count

    total = video_frame_count(video) if total is None else total
    if span:
        cap = open_capture(str(video))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        cap.release()
        total = span.frames(total, fps)
    keep = set(analysed_frames(total, max_frames).tolist()) if total else None
    finder = FaceFinder.load()
    images, marks, found, faces, times = [], [], [], [], []
    prev = None
    prog = Progress(len(keep) if keep else 0, "landmarks", quiet=quiet)
    t_first, t_last, n_read, size = None, 0.0, 0, (0, 0)
    for k, (_, t, img) in enumerate(iter_video(video, span)):
        n_read, t_last = k + 1, t
        t_first = t if t_first is None else t_first
        if keep is not None and k not in keep:
            continue
        times.append(t)
        size = (img.shape[1], img.shape[0])
        face = finder.track(img, prev) if prev is not None else None
        face = face or finder.find(img)
        prev = face
        images.append(img)
        faces.append(face)
        marks.append(face.landmarks if face is not None else np.full((478, 3), np.nan))
        found.append(face is not None)
        prog.update()
        if progress is not None:
            progress("landmarks", len(images), len(keep) if keep else 0)
    prog.close()
    if total and n_read < total * 0.9 and not span:
        print(f"articast enroll: warning: {video} ended early: read {n_read} of the {total} "
              "frames its container declares", file=sys.stderr)
    length = t_last - (t_first or 0.0)
    fps_dt = length / max(n_read - 1, 1)
    readings = None
    if read:
        reader = reader_finder()  # the live reader, cropping as it will live
        prog = Progress(len(images), "reader landmarks", quiet=quiet)

        def step() -> None:
            prog.update()
            if progress is not None:
                progress("reader landmarks", prog.done, len(images))
        readings = read_every_frame(reader, images, faces, progress=step)
        prog.close()
    return (images, np.array(marks), np.array(found, bool), length + fps_dt, size, n_read,
            readings, np.array(times))


@dataclass(frozen=True)
class EnrolSettings:
    """What ``articast enroll``'s options say (its defaults), for :func:`enrol_speaker`."""
    rig: str = "desk"
    ipd_mm: float = 63.0
    mouth_width_mm: float = 50.0
    depth: str = "rigid"
    flow: bool | None = None
    kind: str = "la_quad"
    max_frames: int = 600
    name: str = ""
    delegate: bool = True
    contact_sheet: bool = True
    camera: Path | None = None
    span: Any = None
    """A :class:`articast.service.video.Span` of the clip, or None: all of it."""
    total: int | None = None
    """The clip's frame count when counted by the caller (None: the container's)."""
    label: str = ""
    """How errors name the clip (default its path)."""


@dataclass
class Enrolment:
    """What :func:`enrol_speaker` wrote: the speaker, its report (``speaker.json``'s), the
    warnings, and the contact sheet's tile count (0: none)."""
    speaker: Any
    report: dict[str, Any]
    warnings: list[str]
    sheet: int


def enrol_speaker(video: Path, output: Path, opts: EnrolSettings, quiet: bool = True,
                  progress: Callable[[str, int, int], None] | None = None) -> Enrolment:
    """The enrolment of ``articast enroll``: the speaker folder ``output`` from ``video``
    (InputError in one line when the clip cannot be enrolled). ``progress(stage, done, of)``
    is told of each stage (``landmarks``, ``reader landmarks``, ``model``, ``delegate``,
    ``contact sheet``; ``of`` 0 when a stage has no count)."""
    from articast.core.faces.build import BuildOptions, build_speaker
    from articast.core.faces.enrol import EnrolOptions
    from articast.core.faces.live import FusionPolicy
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.model.camera import Camera

    tell = progress or (lambda stage, done, of: None)
    for what, v in (("ipd-mm", opts.ipd_mm), ("mouth-width-mm", opts.mouth_width_mm)):
        if not (np.isfinite(v) and 10.0 <= v <= 150.0):
            raise InputError(f"--{what} must be between 10 and 150 mm")
    if opts.max_frames < 20:
        raise InputError("--max-frames must be at least 20")
    if output.exists() and not output.is_dir():
        raise InputError(f"{output}: exists and is not a folder")
    label = opts.label or str(video)
    camera = Camera.load(opts.camera) if opts.camera else None
    # fused live tracking reads FaceMesh v1 every frame on a desk camera (not on a
    # head-mounted one: core/faces/live.py LivePolicy.fusion)
    images, marks, found, seconds, size, n_read, readings, times = find_faces(
        video, opts.max_frames, quiet, opts.span, read=opts.rig == "desk", total=opts.total,
        progress=progress)
    if camera is None:
        camera = Camera.default(size[0], size[1], DEFAULT_FOV_DEG)
    else:  # the same camera at another resolution is scaled; another aspect ratio: one line
        from articast.service.processors import fit_camera, scaling_note

        note = scaling_note(camera, *size)
        camera = fit_camera(camera, size[0], size[1], what="the video's frames")
        if note and not quiet:
            print(f"articast enroll: {note}", file=sys.stderr)
    warnings = []
    if seconds < MIN_SECONDS:
        warnings.append(f"the clip is {seconds:.1f} s long: 20-60 s of reading aloud cover "
                        "the articulation far better")
    if found.mean() < 0.5:
        raise InputError(f"{label}: a face was found in {found.sum()} of {found.size} "
                         "analysed frames: is one face in view and lit?")
    scheme = mediapipe_scheme(opts.rig, opts.ipd_mm)

    said = [0]

    def say(m: str) -> None:  # (build_speaker says ~5 things: training, refining, reader, eyes)
        said[0] += 1
        tell("model", min(said[0], 5), 6)
        if not quiet:
            print(f"enroll: {m}", file=sys.stderr)
    tell("model", 0, 0)
    speaker = build_speaker(
        images, marks, found, scheme, camera, opts.rig,
        EnrolOptions(ipd_mm=opts.ipd_mm, mouth_width_mm=opts.mouth_width_mm,
                     fixed_pose=(opts.rig == "head"), depth=opts.depth),
        BuildOptions(kind=opts.kind, flow=opts.flow), opts.name or video.stem, say,
        readings=readings, times=times,
        reader_keep_roi=FusionPolicy().reader_keep_roi if readings is not None else None)
    cov = speaker.report["coverage"]
    ap_range = cov["aperture_mm"][1] - cov["aperture_mm"][0]
    wd_range = cov["width_mm"][1] - cov["width_mm"][0]
    if ap_range < MIN_APERTURE_RANGE_MM:
        warnings.append(f"the lips opened by {ap_range:.1f} mm at most: read with open "
                        "vowels ('a') so jaw opening is covered")
    if wd_range < MIN_WIDTH_RANGE_MM:
        warnings.append(f"the mouth width varied by {wd_range:.1f} mm only: include spread "
                        "and rounded vowels ('ee', 'oo')")
    up = speaker.report.get("upper")
    if up is not None and not up.get("eyes_visible"):
        warnings.append("the eyes were not visible in enough frames: eyes and brows will be "
                        "reported absent ('not_calibrated')")
    elif up is not None and up.get("blinks", 0) == 0:
        from articast.core.faces.upper import CLOSED_FRACTION

        warnings.append(f"the clip holds no blink: the closed eye is assumed at "
                        f"{100 * CLOSED_FRACTION:.0f} % of the open eye's lid opening (blink "
                        f"naturally while reading)")
    report = {**speaker.report, "seconds": round(seconds, 2), "frames_read": n_read,
              "frames_analysed": int(found.size),
              "camera": "given" if opts.camera else f"default ({DEFAULT_FOV_DEG:g} deg)",
              "warnings": warnings}
    from dataclasses import replace

    speaker = replace(speaker, report=report)
    speaker.save(output)
    if opts.delegate:
        tell("delegate", 0, 0)
        report["delegate"] = _write_delegate(
            output, speaker, images, found, times,
            (lambda m: None) if quiet else (lambda m: print(f"enroll: {m}", file=sys.stderr)))
    sheet = 0
    if opts.contact_sheet:
        tell("contact sheet", 0, 0)
        sheet = write_contact_sheet(output / CONTACT_SHEET, speaker, images, found)
    return Enrolment(speaker, report, warnings, sheet)


def _enroll(args: argparse.Namespace) -> int:
    from articast.service.video import Span

    done = enrol_speaker(args.video, args.output, EnrolSettings(
        rig=args.rig, ipd_mm=args.ipd_mm, mouth_width_mm=args.mouth_width_mm,
        depth=args.depth, flow=args.flow, kind=args.kind, max_frames=args.max_frames,
        name=args.name, delegate=args.delegate, camera=args.camera,
        span=Span(args.start, args.end)), quiet=args.quiet)
    speaker, report, sheet = done.speaker, done.report, done.sheet
    if args.json:
        print(dumps({"speaker": str(args.output), "residual": speaker.residual.to_dict(),
                     **report}, indent=1))
    else:
        _print_report(args.output, speaker, report)
        if sheet:
            print(f"contact sheet: {args.output / CONTACT_SHEET} (the fitted model on "
                  f"{sheet} enrolment frames: lips outer yellow, inner magenta)")
    for w in done.warnings:
        print(f"articast enroll: warning: {w}", file=sys.stderr)
    return 0


CONTACT_SHEET = "contact.png"


def _write_delegate(folder: Path, speaker, images: list, found: np.ndarray, times: np.ndarray,
                    say) -> dict | str:
    """delegate.npz from the enrolment's frames (``articast delegate``); its report, or why
    there is none (the speaker folder is complete without it)."""
    from articast.core.delegate.build import DELEGATE_FILE
    from articast.service.commands.delegate import make_delegate

    keep = np.flatnonzero(found)
    try:
        d = make_delegate(speaker, [images[i] for i in keep], np.asarray(times)[keep], say)
    except ArticastError as exc:  # the speaker folder is complete without it
        print(f"articast enroll: warning: no delegate: {exc}", file=sys.stderr)
        return f"none: {exc}"
    d.save(folder / DELEGATE_FILE)
    return d.report


def write_contact_sheet(path: Path, speaker, images: list, found: np.ndarray,
                        n: int = 6) -> int:
    """``n`` enrolment frames spread over the clip, each fitted afresh by the live tracker
    (landmarks, then the appearance fit) and drawn as ``track --overlay`` draws: what the
    enrolment learned, to look at before trusting it. Returns the number of tiles (0 when
    no frame could be fitted; the folder is complete without the sheet)."""
    import cv2

    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker, live_policy
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.service.overlay import fit_tile, grid, label, lip_contours

    contours = lip_contours(speaker)
    usable = np.flatnonzero(found)
    tiles = []
    finder = FaceFinder.load()
    for i in usable[np.linspace(0, len(usable) - 1, min(n, len(usable))).round().astype(int)]:
        live = LiveTracker(speaker, finder, mediapipe_scheme(speaker.rig),
                           tracking=live_policy(speaker.rig))
        res = live.track(images[i], 0.0)
        tile = fit_tile(images[i], speaker.model, speaker.camera, res, contours, size=240)
        lips = res.lips or {}
        tiles.append(label(tile, f"#{i} {lips.get('aperture_mm', float('nan')):.1f} mm"
                           + ("" if res.ok else f" {res.reason.split(':')[0]}")))
    if not tiles:
        return 0
    if not cv2.imwrite(str(path), grid(tiles)):
        print(f"articast enroll: warning: could not write {path}", file=sys.stderr)
        return 0
    return len(tiles)


def _print_report(folder: Path, speaker, report: dict) -> None:
    var = report["variance_pct"]
    print(f"speaker folder: {folder}")
    print(f"clip: {report['seconds']:.1f} s, {report['frames_analysed']} frames analysed, "
          f"{report['frames_used']} used, {len(report['rejected'])} rejected")
    for why, n in Counter(report["rejected"].values()).most_common():
        print(f"  rejected {n}: {why}")
    print("variance explained (%): " + ", ".join(f"{k} {v:.1f}" for k, v in var.items())
          + f"; total {sum(var.values()):.1f}")
    print("lar1 (throat) is not visible to the camera: it stays 0")
    d = report.get("delegate")
    if isinstance(d, dict):
        print(f"delegate: {folder / 'delegate.npz'} (textured from {d['frames']} tracked "
              f"frames, {d['texels_seen_pct']} % of the face seen; 'articast export-gltf')")
    print(f"scale: {report['scale']}; camera: {report['camera']}")
    cov = report["coverage"]
    print(f"lip aperture {cov['aperture_mm'][0]:.1f}-{cov['aperture_mm'][1]:.1f} mm, "
          f"width {cov['width_mm'][0]:.1f}-{cov['width_mm'][1]:.1f} mm "
          "(2nd-98th percentile of the clip)")
    up = report.get("upper")
    if up and up.get("eyes_visible"):
        o, c, b = up["open_eye_mm"], up["closed_eye_mm"], up["neutral_brows_mm"]
        print(f"eyes: open {o[0]:.1f} / {o[1]:.1f} mm, closed {c[0]:.1f} / {c[1]:.1f} mm "
              f"(left / right lid opening), {up['blinks']} blinks in {up['frames']} frames; "
              f"neutral brows {b[0]:.1f} / {b[2]:.1f} mm (inner, left / right) above the eyes")
        ir = up.get("iris_radius_mm") or [0.0, 0.0]
        if min(ir) > 0:
            print(f"irises: radius {ir[0]:.1f} / {ir[1]:.1f} mm (the gaze's circle)")
        else:
            print("irises: not measured (no iris/white contrast): the gaze is fitted to each "
                  "frame's own widest iris chord")
        watched = [side for side, w in zip(("left", "right"), up.get("watched") or [],
                                           strict=False) if w]
        if watched:
            print(f"blinks between readings: the {' and '.join(watched)} eye's pixels do not "
                  "follow its lids; a frame where it changes is read for it")
    r = speaker.residual
    print(f"appearance: {report['appearance']['kind']}, {report['appearance']['sample_points']} "
          f"points, trained on {report['training_frames']} frames; residual on "
          f"{r.frames} held-out frames: median {r.median:.3g}, p99 {r.p99:.3g}")
