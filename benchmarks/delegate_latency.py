"""The browser avatar drawing a speaker's delegate keeps the latency of the generic face:
headless Chromium (SwiftShader) against an in-process server replaying, at 60 Hz, a talking
recording made with the speaker's own model, for SECONDS s, with and without the delegate
(``delegates=False`` is ``serve --no-delegate``). Prints, per run, the server's and the
page's rates and the latency (capture -> drawn) median and p95, as tests/
test_avatar_latency.py measures the generic face.

    python benchmarks/delegate_latency.py SPEAKER_DIR [--seconds 30]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from articast.core.faces.speaker import Speaker  # noqa: E402
from articast.service.app import ServiceConfig  # noqa: E402
from articast.service.settings import ServerSettings  # noqa: E402
from articast.service.worker import SessionSpec  # noqa: E402
from tests.browser import Browser  # noqa: E402
from tests.service_helpers import ServerThread  # noqa: E402
from tests.test_avatar_latency import talking_recording  # noqa: E402

FPS = 60.0


def recording(path: Path, speaker: Speaker, frames: int = 240) -> Path:
    """The speaker's own model talking at 60 Hz, 1.5 s.d., face-on at 450 mm."""
    return talking_recording(path, FPS, frames, speaker.model, speaker.camera, 1.5,
                             {"rotation": [3.14159, 0.0, 0.0], "translation": [0.0, 0.0, 450.0]})


def run(spec: SessionSpec, delegates: bool, seconds: float) -> dict:
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=(spec,),
                           delegates=delegates)
    with ServerThread(config) as srv, \
            Browser(f"http://127.0.0.1:{srv.port}/avatar/?session=talk") as b:
        b.wait_for("window.articast.rendered > 30", 60)
        b.wait_for("window.articast.mesh.startsWith('dense')", 60)
        if delegates:
            b.wait_for("window.articast.delegate.startsWith('textured')", 60)
        time.sleep(2.0)
        skip = b.evaluate("window.articast.latencies.length")
        f0, d0, t0 = b.evaluate("window.articast.frames"), b.evaluate(
            "window.articast.rendered"), time.monotonic()
        time.sleep(seconds)
        el = time.monotonic() - t0
        f1, d1 = b.evaluate("window.articast.frames"), b.evaluate("window.articast.rendered")
        lat = np.array(b.evaluate(f"window.articast.latencies.slice({skip})"), float)
    return {"delegate": delegates, "received_hz": round((f1 - f0) / el, 1),
            "drawn_hz": round((d1 - d0) / el, 1),
            "latency_ms_median": round(float(np.median(lat)), 1),
            "latency_ms_p95": round(float(np.percentile(lat, 95)), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("speaker", type=Path, help="speaker folder with a delegate.npz")
    ap.add_argument("--seconds", type=float, default=30.0)
    args = ap.parse_args()
    speaker = Speaker.load(args.speaker)
    with tempfile.TemporaryDirectory() as tmp:
        rec = recording(Path(tmp) / "talk.jsonl", speaker)
        spec = SessionSpec("talk", f"replay-record:{rec}?loop=yes", processor="truth",
                           speaker=str(args.speaker))
        for delegates in (True, False):
            print(json.dumps(run(spec, delegates, args.seconds)), flush=True)


if __name__ == "__main__":
    main()
