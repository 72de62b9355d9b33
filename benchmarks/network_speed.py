"""CPU per call of the bundled face networks, one thread, on real crops; optionally against
another copy of the same networks (the same inputs, the two taking turns).

Why: the live reader's network is most of the FaceMesh v1 loop's cost and a part of
articast's, so a change in how the networks run moves both. ``--against DIR`` runs the
files of another folder (e.g. the models before tools/convert_face_models.py wrote each PRelu
as Relu + Sub + Mul + Add: ``git show 9aa0924:core/faces/models/face_landmarks_v1.onnx``)
in turns of ``--chunk`` calls with the bundled ones, reports each one's CPU per call and
the ratio, and the largest output difference between the two (0 for an exact rewrite).

Inputs: crops of the synthetic speaker's render (no data needed), or, with ``--clip``, the
centre squares of a video's first frames.

    python benchmarks/network_speed.py [--against DIR] [--clip VIDEO] [--calls 200] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from articast.core.faces.finder import DETECTOR_FILE, LANDMARK_MODELS, models_dir

NETWORKS = {"face_landmarks_v1": LANDMARK_MODELS["v1"], "face_landmarks_v2": LANDMARK_MODELS["v2"],
            "face_detector": DETECTOR_FILE}


def session(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def frames(clip: Path | None, n: int = 8) -> list[np.ndarray]:
    """``n`` BGR frames: the clip's first ones, or renders of the synthetic speaker."""
    if clip is not None:
        cap = cv2.VideoCapture(str(clip))
        out = []
        while len(out) < n:
            ok, f = cap.read()
            if not ok:
                break
            out.append(f)
        if not out:
            raise SystemExit(f"{clip}: no frame could be read")
        return out
    from articast.core.synthetic import RenderOptions, default_speaker, make_sequence

    speaker = default_speaker(0)
    seq = make_sequence(0, n * 10, 50.0, "desk", size=(640, 480), geometry=speaker.geometry)
    return [speaker.render(seq.controls[i], seq.pose(i), seq.camera, RenderOptions(seed=i))
            for i in range(0, n * 10, 10)]


def inputs(images: list[np.ndarray], size: int, detector: bool) -> list[np.ndarray]:
    """Each image's centre square at the network's input size, in its input range."""
    out = []
    for f in images:
        h, w = f.shape[:2]
        s = min(h, w)
        sq = f[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
        x = cv2.cvtColor(cv2.resize(sq, (size, size), interpolation=cv2.INTER_AREA),
                         cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        out.append((x * 2.0 - 1.0 if detector else x)[None])
    return out


def cpu_per_call(sessions: dict[str, object], xs: list[np.ndarray], calls: int, chunk: int
                 ) -> dict[str, list[float]]:
    """CPU ms per call of each session, in turns of ``chunk`` calls; one value per turn."""
    name = {k: s.get_inputs()[0].name for k, s in sessions.items()}  # type: ignore[attr-defined]
    for k, s in sessions.items():  # warm-up: the first calls allocate
        for x in xs[:3]:
            s.run(None, {name[k]: x})  # type: ignore[attr-defined]
    out: dict[str, list[float]] = {k: [] for k in sessions}
    done = 0
    while done < calls:
        for k, s in sessions.items():
            c0 = time.process_time()
            for i in range(chunk):
                s.run(None, {name[k]: xs[(done + i) % len(xs)]})  # type: ignore[attr-defined]
            out[k].append((time.process_time() - c0) * 1e3 / chunk)
        done += chunk
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[2:]))
    ap.add_argument("--against", type=Path, metavar="DIR",
                    help="a folder with other copies of the networks' files, run in turns")
    ap.add_argument("--clip", type=Path, help="crops of this video's first frames (default: "
                    "the synthetic speaker's renders)")
    ap.add_argument("--calls", type=int, default=200, help="calls per network and copy")
    ap.add_argument("--chunk", type=int, default=20, help="calls per turn")
    ap.add_argument("--json", action="store_true", help="print JSON")
    args = ap.parse_args(argv)
    if args.calls < args.chunk or args.chunk < 1:
        raise SystemExit("--calls must be >= --chunk >= 1")
    images = frames(args.clip)
    load0 = os.getloadavg()
    report: dict = {"command": " ".join(["benchmarks/network_speed.py", *(argv or sys.argv[1:])]),
                    "threads": 1, "calls": args.calls, "networks": {}}
    for key, file in NETWORKS.items():
        mine = session(models_dir() / file)
        shape = mine.get_inputs()[0].shape
        xs = inputs(images, int(shape[1]), key == "face_detector")
        sessions = {"bundled": mine}
        if args.against is not None:
            other = args.against / file
            if not other.is_file():
                raise SystemExit(f"{other}: no such file")
            sessions["against"] = session(other)
        per = cpu_per_call(sessions, xs, args.calls, args.chunk)
        row: dict = {k: {"cpu_ms_median": round(float(np.median(v)), 3),
                         "cpu_ms_min": round(float(np.min(v)), 3),
                         "cpu_ms_max": round(float(np.max(v)), 3)} for k, v in per.items()}
        if "against" in sessions:
            ratios = np.array(per["bundled"]) / np.array(per["against"])
            row["bundled_over_against"] = {"median": round(float(np.median(ratios)), 3),
                                           "min": round(float(ratios.min()), 3),
                                           "max": round(float(ratios.max()), 3)}
            diff = 0.0
            for x in xs:
                a = mine.run(None, {mine.get_inputs()[0].name: x})
                b = sessions["against"].run(None, {sessions["against"].get_inputs()[0].name: x})  # type: ignore[attr-defined]
                diff = max(diff, *(float(np.abs(p - q).max()) for p, q in zip(a, b, strict=True)))
            row["max_abs_output_difference"] = diff
        report["networks"][key] = row
    report["load_average"] = {"start": [round(v, 2) for v in load0],
                              "end": [round(v, 2) for v in os.getloadavg()]}
    if args.json:
        print(json.dumps(report, indent=1))
        return
    for key, row in report["networks"].items():
        parts = [f"{k} {v['cpu_ms_median']:.2f} ms ({v['cpu_ms_min']:.2f}-{v['cpu_ms_max']:.2f})"
                 for k, v in row.items() if isinstance(v, dict) and "cpu_ms_median" in v]
        extra = ""
        if "bundled_over_against" in row:
            r = row["bundled_over_against"]
            extra = (f"; bundled / against {r['median']:.3f} ({r['min']:.3f}-{r['max']:.3f}), "
                     f"max |difference| {row['max_abs_output_difference']:.3g}")
        print(f"{key}: " + ", ".join(parts) + extra)
    print(f"load {report['load_average']['start']} -> {report['load_average']['end']}")


if __name__ == "__main__":
    main()
