"""The meeting room with N participants in real headless Chromium (issue 41): capture to remote
screen latency, the animation's offset from the audio's playout, and CPU per participant as a
multiple of the FaceMesh v1 loop.

    python benchmarks/room.py [--participants 2] [--seconds 40] [--json]

Each participant is one Chromium process with a fake camera and microphone fed from a clip of
the synthetic speaker (tests/test_room.py makes them); the server runs in this process.

- ``latency_ms``: per frame a remote page applied, when it was applied minus when the server
  received its video frame (``t_capture``, on the page's clock); p50/p95 over every remote
  pair. It includes the delay the page adds on purpose to wait for the audio.
- ``av_offset_ms``: applied minus due (due = ``t_capture`` + the measured audio delay D):
  how much later than its voice a frame was shown (0 when on time; positive: lips lag the
  voice). Median and p5-p95.
- ``voice``: per remote pair at the end, the voice's measured delay D, the jitter-buffer
  target the page asked for, and the share of played samples the jitter buffer concealed.
- ``cpu_x_v1``: one participant's CPU per tracked frame (their worker process, plus a 1/N
  share of this process (the room's sockets) and of the media process (WebRTC, decoding,
  the audio relay)) over the
  CPU per frame of the FaceMesh v1 loop (benchmarks/peers.py's ``facemesh_v1_finder``, one
  thread) on the same clip's frames.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def v1_loop_cpu_ms(frames: list[np.ndarray]) -> float:
    """CPU ms per frame of the FaceMesh v1 loop (benchmarks/peers.py's FinderLoop: the
    detector when lost, else the landmarks in a crop grown from the last reading), one
    thread, after a warm-up pass."""
    from peers import FinderLoop, facemesh_v1_finder

    from articast.core.faces.finder import models_dir

    loop = FinderLoop(facemesh_v1_finder(models_dir() / "face_landmarks_v1.onnx"), frames)
    for i in range(len(frames)):
        loop(i)
    t0 = time.process_time()
    for i in range(len(frames)):
        loop(i)
    return 1000 * (time.process_time() - t0) / len(frames)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=40.0,
                    help="measured after every page receives every other's frames")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    from tests.service_helpers import ServerThread
    from tests.test_room import SLOW, config, make_clip, participant

    tmp = Path(tempfile.mkdtemp(prefix="articast-room-bench-"))
    names = [f"p{i}" for i in range(args.participants)]
    clips = {n: make_clip(tmp / n, 1, 450 * i, n=90 * SLOW, slow=SLOW)
             for i, n in enumerate(names)}
    browsers = []
    with ServerThread(config()) as srv:
        try:
            for n in names:
                browsers.append(participant(srv, n, clips[n]).__enter__())
            every = " && ".join(
                f"(window.articastRoom.members[{json.dumps(o)}] || {{received: []}})"
                ".received.length > 10" for o in names)
            for b in browsers:
                b.wait_for(every, timeout=900)
            sessions = srv.service.manager.sessions
            pids = {n: sessions[n]._worker.process.pid for n in names}
            media_pid = srv.service.media._proc.pid
            cpu0 = {n: proc_cpu_s(p) for n, p in pids.items()}
            media0 = proc_cpu_s(media_pid)
            frames0 = {n: sessions[n].metrics.frames for n in names}
            rejoined0 = [b.evaluate("window.articastRoom.rejoined.length") for b in browsers]
            own0, t0 = time.process_time(), time.monotonic()
            load0 = os.getloadavg()[0]
            time.sleep(args.seconds)
            wall = time.monotonic() - t0
            own = time.process_time() - own0
            # a connection that dropped meanwhile (its page joins again: a new worker, maybe
            # a new media process) leaves no steady figure: said in one line, not measured
            rejoined = {n: b.evaluate("window.articastRoom.rejoined.length") - r0
                        for n, b, r0 in zip(names, browsers, rejoined0, strict=True)}
            if any(rejoined.values()) or not all(Path(f"/proc/{p}").exists() for p in (
                    media_pid, *pids.values())):
                raise SystemExit(f"{args.participants} participants: connections dropped "
                                 f"during the measurement (rejoins per page: {rejoined}): "
                                 "this machine does not hold them at this load")
            media = proc_cpu_s(media_pid) - media0
            cpu = {n: proc_cpu_s(p) - cpu0[n] for n, p in pids.items()}
            frames = {n: sessions[n].metrics.frames - frames0[n] for n in names}
            lat, off, voice = [], [], []
            start_ms = (time.time() - wall) * 1000
            for n, b in zip(names, browsers, strict=True):
                for o in names:
                    if o == n:
                        continue
                    rows = json.loads(b.evaluate(
                        f"JSON.stringify(window.articastRoom.members[{json.dumps(o)}].applied)"))
                    offset = b.evaluate("window.articastRoom.offsetMs")
                    voice.append(json.loads(b.evaluate(
                        f"(() => {{ const m = window.articastRoom.members[{json.dumps(o)}];"
                        " return JSON.stringify({delay: m.audioDelayMs, target: m.jitterTarget,"
                        " arrival: m.arrival}); })()")))
                    for _t, _a, t_capture, applied, due in rows:
                        if applied < start_ms:
                            continue
                        lat.append(applied - (t_capture * 1000 + offset))
                        off.append(applied - due)
        finally:
            for b in browsers:
                b.close()
    import cv2

    cap = cv2.VideoCapture(str(clips[names[0]]["y4m"]))
    imgs = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        imgs.append(img)
    v1 = v1_loop_cpu_ms(imgs)
    shared = own + media  # this process and the media process, for every participant
    per = {n: 1000 * (cpu[n] + shared / len(names)) / max(frames[n], 1) for n in names}
    out = {
        "participants": args.participants, "seconds": round(wall, 1),
        "load_1min_at_start": round(load0, 1), "cores": os.cpu_count(),
        "latency_ms": {"p50": round(float(np.percentile(lat, 50)), 1),
                       "p95": round(float(np.percentile(lat, 95)), 1), "n": len(lat)},
        "av_offset_ms": {"median": round(float(np.median(off)), 1),
                         "p5": round(float(np.percentile(off, 5)), 1),
                         "p95": round(float(np.percentile(off, 95)), 1)},
        "voice": {
            "delay_ms": [None if v["delay"] is None else round(v["delay"]) for v in voice],
            "jitter_target_ms": [None if v["target"] is None else round(v["target"])
                                 for v in voice],
            "concealed": [None if not v["arrival"] or v["arrival"]["concealed"] is None
                          else round(v["arrival"]["concealed"], 3) for v in voice]},
        "tracked_fps": {n: round(frames[n] / wall, 1) for n in names},
        "cpu_ms_per_frame": {n: round(v, 1) for n, v in per.items()},
        "v1_loop_cpu_ms_per_frame": round(v1, 1),
        "cpu_x_v1": {n: round(v / v1, 2) for n, v in per.items()},
        "cpu_s": {"workers": {n: round(v, 1) for n, v in cpu.items()},
                  "server": round(own, 1), "media_process": round(media, 1)},
    }
    print(json.dumps(out, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
