"""What the page's frame-rate cap saves the room's media process (docs/ROOM.md, "Tracking is
slow here").

One headless Chromium joins a room on loopback with its fake camera (640x480, 30 fps) and is
tracked by a processor that only reads the image (the cost measured is the media process's:
receiving and decoding the video, not the tracker's); for each cap (``RoomConfig.max_fps``,
0: none) the video frames the server received per second and the media process's CPU are
measured over ``--seconds``.

    python benchmarks/room_framerate.py --caps 0,15,8 --seconds 15
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def speaker_clip(path: Path, frames: int = 90) -> Path:
    """3 s of the synthetic speaker talking, as .y4m (what Chromium's fake camera reads): a
    face's detail costs the decoder what a real camera's does (its default pattern is
    mostly flat)."""
    if path.exists():
        return path
    from articast.core.synthetic import open_stream
    from articast.service.sources import cache_dir
    from tests.test_webrtc import write_y4m

    images = []
    for _, image, _ in open_stream(seed=1, fps=30.0, cache_dir=cache_dir()).frames():
        images.append(image)
        if len(images) == frames:
            break
    return write_y4m(path, images, 30)


def run(cap: float, seconds: float, clip: Path | None) -> dict:
    from articast.service.app import ServiceConfig
    from articast.service.room import RoomConfig
    from articast.service.security import AccessPolicy
    from tests.browser import Browser
    from tests.service_helpers import ServerThread

    token = "room-token-for-the-benchmark-0123"
    config = ServiceConfig(access=AccessPolicy(token="operator-token-for-the-bench-0"),
                           room=RoomConfig(name="b", token=token, max_fps=cap,
                                           processor="tests.service_helpers:ImageStats"))
    flags: tuple[str, ...] = ("--use-fake-device-for-media-stream",
                              "--use-fake-ui-for-media-stream")
    if clip is not None:
        flags += (f"--use-file-for-fake-video-capture={clip}",)
    with ServerThread(config) as srv:
        url = f"{srv.http}/room?room={token}&name=ann&audio=0"
        with Browser(url, flags=flags) as b:
            b.wait_for("window.articastRoom.joined", timeout=120)
            room = srv.server.config.loaded_app.app.state.room
            deadline = time.monotonic() + 60
            while "ann" not in room.members or room.members["ann"].feed is None or \
                    room.members["ann"].feed.received < 10:
                assert time.monotonic() < deadline, "no video arrived"
                time.sleep(0.2)
            time.sleep(3.0)  # past the connection's start
            feed, pid = room.members["ann"].feed, srv.service.media._proc.pid
            n0, c0, t0 = feed.received, cpu_s(pid), time.monotonic()
            time.sleep(seconds)
            n1, c1, t1 = feed.received, cpu_s(pid), time.monotonic()
            sent_cap = b.evaluate("window.articastRoom.maxFramerate")
            size = feed.size
    return {"cap": cap, "sender_maxFramerate": sent_cap, "received_fps": (n1 - n0) / (t1 - t0),
            "media_cpu_per_s": (c1 - c0) / (t1 - t0), "size": list(size),
            "load": os.getloadavg()[0]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--caps", default="0,15", help="comma-separated caps (0: none)")
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--clip", type=Path, default=Path("/tmp/articast-room-framerate.y4m"),
                   help="the fake camera's .y4m (made from the synthetic speaker if missing)")
    p.add_argument("--pattern", action="store_true",
                   help="Chromium's own fake camera pattern instead of the clip")
    args = p.parse_args()
    clip = None if args.pattern else speaker_clip(args.clip)
    for cap in (float(c) for c in args.caps.split(",")):
        print(json.dumps({"load_before": os.getloadavg()[0], **run(cap, args.seconds, clip)}),
              flush=True)


if __name__ == "__main__":
    main()
