"""What Chromium's fake camera sends over WebRTC, without our server (issue 41's diagnosis).

    python benchmarks/fake_camera.py [--participants 2] [--seconds 20] [--json]

The room test (tests/test_room.py) maps each streamed frame to a frame of the looped clip by
its media time (``round(t * fps)``). This checks that mapping and the video itself: each
participant is one headless Chromium on the join page (clients/web/join.html) with a fake
camera reading the room test's clip, each frame marked with its index (7 black/white blocks
in the bottom-left corner, away from the face); a bare aiortc receiver on its own loop (no
tracking, no room) answers the offers and reads, per decoded frame, its media time, its size
and its marked index. Reported per participant: frames received per second, the sizes seen,
the share of frames whose marker reads, and how far the marked index is from the one the
media time predicts (after the best constant shift): 0 everywhere when the fake camera keeps
time; otherwise the mapping, not the tracker, blurs the correlation.
"""

import argparse
import asyncio
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

BITS, BLOCK, X0, Y0 = 7, 16, 8, 448

def mark(image: np.ndarray, index: int) -> np.ndarray:
    out = image.copy()
    for k in range(BITS):
        value = 255 if (index >> k) & 1 else 0
        out[Y0:Y0 + BLOCK, X0 + k * BLOCK:X0 + (k + 1) * BLOCK] = value
    return out

def read_mark(gray: np.ndarray) -> int | None:
    index = 0
    for k in range(BITS):
        block = gray[Y0 + 3:Y0 + BLOCK - 3, X0 + k * BLOCK + 3:X0 + (k + 1) * BLOCK - 3]
        m = float(block.mean())
        if 60 < m < 195:
            return None
        index |= (m >= 128) << k
    return index

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import cv2
    import uvicorn
    from aiortc import RTCPeerConnection, RTCSessionDescription
    from fastapi import FastAPI, Request
    from fastapi.staticfiles import StaticFiles

    from tests.browser import Browser
    from tests.test_room import FAKE, FPS, SEED, make_clip
    from tests.test_webrtc import write_y4m

    tmp = Path(tempfile.mkdtemp(prefix="articast-fake-camera-"))
    clips = []
    for i in range(args.participants):
        clip = make_clip(tmp / f"p{i}", SEED, 150 * i)
        raw = clip["y4m"].read_bytes()
        header, _, body = raw.partition(b"\n")
        w = int(next(t for t in header.split() if t.startswith(b"W"))[1:])
        h = int(next(t for t in header.split() if t.startswith(b"H"))[1:])
        n = w * h * 3 // 2
        frames = [cv2.cvtColor(np.frombuffer(c[:n], np.uint8).reshape(h * 3 // 2, w),
                               cv2.COLOR_YUV2BGR_I420) for c in body.split(b"FRAME\n")[1:]]
        clips.append((write_y4m(tmp / f"p{i}" / "marked.y4m",
                                [mark(f, k) for k, f in enumerate(frames)], FPS),
                      clip["wav"], len(frames)))

    seen: dict[str, list[tuple[float, int | None, int, int, float]]] = {}
    app = FastAPI()
    pcs = []

    @app.post("/api/sessions/{name}/webrtc")
    async def offer(name: str, request: Request) -> dict[str, str]:
        body = await request.json()
        pc = RTCPeerConnection()
        pcs.append(pc)
        rows = seen.setdefault(name, [])

        @pc.on("track")
        def on_track(track) -> None:  # type: ignore[no-untyped-def]
            async def pump() -> None:
                while True:
                    frame = await track.recv()
                    if track.kind != "video":
                        continue
                    gray = frame.to_ndarray(format="gray")
                    if gray.shape != (480, 640):
                        gray = cv2.resize(gray, (640, 480))
                    rows.append((float(frame.time), read_mark(gray), frame.width, frame.height,
                                 time.monotonic()))

            asyncio.ensure_future(pump())

        await pc.setRemoteDescription(RTCSessionDescription(sdp=body["sdp"], type="offer"))
        await pc.setLocalDescription(await pc.createAnswer())
        return {"type": "answer", "sdp": pc.localDescription.sdp}

    app.mount("/avatar", StaticFiles(directory=ROOT / "clients" / "web"), name="web")
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    port = server.servers[0].sockets[0].getsockname()[1]
    browsers = []
    try:
        for i, (y4m, wav, _) in enumerate(clips):
            flags = (*FAKE, f"--use-file-for-fake-video-capture={y4m}",
                     f"--use-file-for-fake-audio-capture={wav}")
            browsers.append(Browser(f"http://127.0.0.1:{port}/avatar/join.html?session=p{i}"
                                    "&audio=1", flags=flags))
        time.sleep(args.seconds)
        for i, b in enumerate(browsers):
            if not seen.get(f"p{i}"):
                print(f"p{i}: nothing received; the page says",
                      b.evaluate("JSON.stringify(window.articastJoin || null)"), file=sys.stderr)
    finally:
        for b in browsers:
            b.close()
        server.should_exit = True
        thread.join(5)

    report = {}
    for i, (_, _, n) in enumerate(clips):
        rows = seen.get(f"p{i}", [])
        marked = [(t, k) for t, k, *_ in rows if k is not None]
        entry: dict[str, object] = {"received": len(rows)}
        if len(rows) > 1:
            span = rows[-1][4] - rows[0][4]
            entry["fps"] = round((len(rows) - 1) / span, 1) if span > 0 else None
            entry["sizes"] = sorted({f"{w}x{h}" for _, _, w, h, _ in rows})
            entry["marker_read"] = round(len(marked) / len(rows), 3)
        if len(marked) > 5:
            t = np.asarray([m[0] for m in marked])
            k = np.asarray([m[1] for m in marked])
            predicted = np.round((t - t[0]) * FPS).astype(int)
            err = (k - predicted) % n
            err = np.where(err > n // 2, err - n, err)  # circular: -n/2..n/2
            err = err - int(np.median(err))
            entry["index_error_frames"] = {
                "median_abs": float(np.median(np.abs(err))),
                "p95_abs": float(np.percentile(np.abs(err), 95)),
                "max_abs": int(np.max(np.abs(err))),
                "drift_first_to_last": int(err[-1] - err[0])}
        report[f"p{i}"] = entry
    if args.json:
        print(json.dumps(report))
    else:
        for name, entry in report.items():
            print(name, json.dumps(entry))
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
