"""``articast synth``: the built-in synthetic speaker's corpus and sequences with ground truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from articast.service.jsonsafe import dumps

EPILOG_SEQUENCE = """\
files written to DIR:
  video.mp4     the rendered frames (mp4v), what a tracker reads
  truth.jsonl   one JSON object per frame: frame, t (s), alpha {jaw1..lar1} (direct inversion
                of the TRUE 3D points in model.npz: the best any tracker using that model can
                do), pose {rotation (axis-angle, rad), translation (mm)} head -> camera,
                controls {jaw1..lar1} (the generating controls of the synthetic speaker),
                occluded (true where --occluder hides the mouth in this frame) and, with
                --upper, upper {closure_left, closure_right (0 open .. 1 closed),
                gaze_yaw_deg (to the speaker's left +), gaze_pitch_deg (up +),
                raise_left_mm, raise_right_mm (brows)}
  truth.npz     arrays points (F, N, 3) mm head frame, controls (F, 7), poses (F, 6), times,
                still (F,) frames inside still segments (for jitter measurements)
  model.npz     the linear model built from the speaker's corpus (articast build-model)
  camera.json   the camera intrinsics

examples:
  articast synth sequence -o out/talk --rig head --frames 150
  articast synth sequence -o out/desk --rig desk --noise 4 --blur 0.8 --light-drift 20
  articast synth sequence -o out/occl --occluder hand --occlude-frames 40:60
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="built-in synthetic speaker: posture corpus, videos with ground truth",
        description=(
            "The built-in synthetic speaker: a procedural face with 7 non-linear articulatory "
            "controls (jaw1 lips1 lips2 lips3 lips4 jaw2 lar1), rendered with texture, light "
            "and a z-buffer. Use it to try articast without a camera and to measure accuracy "
            "against exact ground truth."
        ),
    )
    ss = p.add_subparsers(dest="synth_command", metavar="WHAT")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    c = ss.add_parser(
        "corpus",
        help="write the 68-posture corpus (input of 'articast build-model')",
        description=(
            "Write the speaker's 68 postures (14 vowels, 52 VCV central frames, rest, preph) as "
            "a posture corpus with their generating controls. Build a model from it with "
            "'articast build-model corpus.npz -o model.npz'."
        ),
    )
    c.add_argument("-o", "--output", type=Path, required=True, help="corpus file (.npz)")
    c.add_argument("--seed", type=int, default=0, help="speaker seed (default 0)")
    c.add_argument("--noise-mm", type=float, default=0.3,
                   help="RMS 3D measurement noise per point, mm (default 0.3)")
    c.set_defaults(func=_corpus)

    s = ss.add_parser(
        "sequence",
        help="render a talking sequence with its ground truth",
        description=(
            "Render the speaker talking (coarticulated postures, head motion, still segments) "
            "and write the video and the ground truth. Rig 'head': head-mounted camera ~22 cm "
            "from the mouth, lower face filling the frame; rig 'desk': desk camera ~56 cm "
            "away, whole face visible, head nods and drifts."
        ),
        epilog=EPILOG_SEQUENCE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    s.add_argument("--seed", type=int, default=0, help="speaker seed (default 0)")
    s.add_argument("--sentence", type=int, default=None, metavar="SEED",
                   help="what the speaker says and how the head moves (default: --seed); "
                        "another value gives the same speaker saying something else, e.g. "
                        "an enrolment clip and a test clip of one person")
    s.add_argument("--rig", choices=("head", "desk"), default="head",
                   help="camera rig (default head)")
    s.add_argument("--frames", type=int, default=150, help="number of frames (default 150)")
    s.add_argument("--fps", type=float, default=50.0, help="frame rate (default 50)")
    s.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    s.add_argument("--noise", type=float, default=2.0,
                   help="sensor noise s.d., grey levels (default 2)")
    s.add_argument("--blur", type=float, default=0.0, help="Gaussian blur s.d., px (default 0)")
    s.add_argument("--gain", type=float, default=1.0, help="global gain (default 1)")
    s.add_argument("--light-drift", type=float, default=0.0, metavar="DEG",
                   help="illumination drift: light azimuth swings +-DEG over the sequence")
    s.add_argument("--occluder", choices=("none", "hand", "black"), default="none",
                   help="hand over the mouth, or black frames (default none)")
    s.add_argument("--occlude-frames", default="", metavar="A:B",
                   help="occlude only frames A..B-1 (default: all frames when --occluder is "
                        "set); truth.jsonl marks them with \"occluded\": true")
    s.add_argument("--still-frames", type=int, default=15,
                   help="length of the still segments, frames (default 15; 0 = none)")
    s.add_argument("--upper", action="store_true",
                   help="the eyes blink (10-20 a minute, some double), look around and the "
                        "brows rise, with their truth in truth.jsonl (\"upper\"); default: "
                        "still, open eyes looking ahead (docs/UPPER_FACE.md)")
    s.set_defaults(func=_sequence)


def _parse_size(text: str) -> tuple[int, int]:
    from articast.core.errors import InputError

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x480, got {text!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise InputError(f"--size {w}x{h} is out of range (16..8192 px)")
    return w, h


def _parse_range(text: str, n_frames: int) -> tuple[int, int]:
    """'A:B' -> (A, B) frame range; '' -> all frames."""
    from articast.core.errors import InputError

    if not text:
        return 0, n_frames
    try:
        a, b = (int(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--occlude-frames must look like 40:60, got {text!r}") from None
    if not 0 <= a < b:
        raise InputError(f"--occlude-frames needs 0 <= A < B, got {text!r}")
    return a, b


def _corpus(args: argparse.Namespace) -> int:
    from articast.core.errors import InputError
    from articast.core.synthetic import make_corpus

    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    corpus = make_corpus(args.seed, args.noise_mm)
    corpus.save(args.output)
    print(f"{len(corpus.posture_names)} postures x {corpus.postures.shape[1]} points "
          f"(seed {args.seed}, noise {args.noise_mm} mm) -> {args.output}")
    return 0


def _sequence(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from articast.core.bundle import save_bundle
    from articast.core.errors import InputError
    from articast.core.model.build import invert
    from articast.core.model.face import PARAM_NAMES
    from articast.core.synthetic import RenderOptions, default_speaker, make_sequence

    width, height = _parse_size(args.size)
    occluded = _parse_range(args.occlude_frames, args.frames) if args.occluder != "none" else None
    sentence = args.seed if args.sentence is None else args.sentence
    if args.seed < 0 or sentence < 0:
        raise InputError(f"--seed and --sentence must be >= 0, got {args.seed}, {sentence}")
    if args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    if not args.fps > 0:
        raise InputError(f"--fps must be > 0, got {args.fps}")
    base = RenderOptions(noise_sigma=args.noise, blur_sigma=args.blur, gain=args.gain,
                         occluder=args.occluder)  # validates the options before any work
    out: Path = args.output
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output directory {out}: {exc}") from None

    speaker = default_speaker(args.seed)
    print("building the speaker's model...", file=sys.stderr)
    model = speaker.model()
    seq = make_sequence(sentence, args.frames, args.fps, args.rig, args.still_frames,
                        size=(width, height), geometry=speaker.geometry)
    alpha = invert(model, seq.points)
    upper = None
    if args.upper:
        from articast.core.synthetic.upper import upper_sequence

        upper = upper_sequence(sentence, seq.n_frames, args.fps)

    video_path = out / "video.mp4"
    writer = cv2.VideoWriter(str(video_path), cv2.VideoWriter.fourcc(*"mp4v"), float(args.fps),
                             (width, height))
    if not writer.isOpened():
        raise InputError(f"cannot write {video_path}: OpenCV has no mp4v encoder here or the "
                         "directory is not writable")
    try:
        with open(out / "truth.jsonl", "w") as fh:
            for i in range(seq.n_frames):
                drift = args.light_drift * np.sin(2 * np.pi * i / max(seq.n_frames, 2))
                hidden = occluded is not None and occluded[0] <= i < occluded[1]
                opts = RenderOptions(
                    noise_sigma=base.noise_sigma, blur_sigma=base.blur_sigma, gain=base.gain,
                    occluder=base.occluder if hidden else "none", seed=sentence * 100_003 + i,
                    light_azimuth_deg=base.light_azimuth_deg + drift,
                )
                up = None if upper is None else upper.frame(i)
                writer.write(speaker.render(seq.controls[i], seq.pose(i), seq.camera, opts, up))
                record = {
                    "frame": i,
                    "t": float(seq.times[i]),
                    "alpha": model.alpha_dict(alpha[i]),
                    "pose": seq.pose(i).to_dict(),
                    "controls": {n: float(v) for n, v in
                                 zip(PARAM_NAMES, seq.controls[i], strict=True)},
                    "occluded": bool(hidden),
                }
                if up is not None:
                    record["upper"] = up
                fh.write(dumps(record) + "\n")
                if (i + 1) % 25 == 0 or i + 1 == seq.n_frames:
                    print(f"\rrendered {i + 1}/{seq.n_frames} frames", end="", file=sys.stderr)
        print("", file=sys.stderr)
    finally:
        writer.release()
    save_bundle(out / "truth.npz", "synthetic-truth", 1,
                {"points": seq.points, "controls": seq.controls, "poses": seq.poses,
                 "times": seq.times, "still": seq.still.astype(np.uint8), "alpha": alpha},
                {"rig": seq.rig, "fps": seq.fps, "seed": args.seed, "sentence": sentence,
                 "control_names": list(PARAM_NAMES), "point_names": list(model.point_names)})
    model.save(out / "model.npz")
    seq.camera.save(out / "camera.json")
    print(f"{seq.n_frames} frames ({args.rig} rig, {width}x{height}, {args.fps:g} fps) -> "
          f"{out}/video.mp4, truth.jsonl, truth.npz, model.npz, camera.json")
    return 0
