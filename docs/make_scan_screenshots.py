"""Render docs/scan_jaw_closed.png and docs/scan_jaw_open.png: menpo3d's james, bound to the
synthetic speaker by its landmarks, textured, in the browser avatar (real headless Chromium)
animated by two streams of the speaker, jaw1 = 0 and jaw1 at the top of its training range.

    python tools/fetch_scan.py
    python docs/make_scan_screenshots.py [--scan DIR] [--output-dir docs]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from articast.core.synthetic import default_speaker  # noqa: E402
from articast.service.app import ServiceConfig  # noqa: E402
from articast.service.cli import main as cli  # noqa: E402
from articast.service.settings import ServerSettings  # noqa: E402
from articast.service.worker import SessionSpec  # noqa: E402
from tests.browser import Browser  # noqa: E402
from tests.service_helpers import ServerThread  # noqa: E402
from tests.test_browser import jaw_recording  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path, default=Path.home() / ".cache/articast/scans")
    ap.add_argument("--output-dir", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    model = default_speaker(0).model()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        model.save(d / "speaker.npz")
        code = cli(["bind-dense", str(args.scan / "james.obj"), "--landmarks",
                    str(args.scan / "james.ljson"), "--model", str(d / "speaker.npz"),
                    "-o", str(d / "james.npz")])
        if code:
            raise SystemExit("bind-dense failed (run python tools/fetch_scan.py first?)")
        jaw_open = float(model.stats.max[0])
        sessions = (
            SessionSpec("closed", f"replay-record:{jaw_recording(d / 'c.jsonl', 0.0)}?loop=yes"),
            SessionSpec("open", f"replay-record:{jaw_recording(d / 'o.jsonl', jaw_open)}"
                                "?loop=yes"))
        config = ServiceConfig(server=ServerSettings(log_level="critical",
                                                     scan=str(d / "james.npz")),
                               sessions=sessions)
        with ServerThread(config) as srv:
            for name in ("closed", "open"):
                with Browser(f"http://127.0.0.1:{srv.port}/avatar/?session={name}") as b:
                    b.wait_for("window.articast.mesh.startsWith('scan')", 90)
                    b.wait_for(f"window.articast.rendered > "
                               f"{b.evaluate('window.articast.rendered') + 5}", 30)
                    time.sleep(0.3)
                    png = b.screenshot()
                img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
                out = args.output_dir / f"scan_jaw_{name}.png"
                cv2.imwrite(str(out), img[:, 100: img.shape[1] - 360])  # the head, not the panel
                print(f"{out}  jaw1 = {0.0 if name == 'closed' else jaw_open:.2f}")


if __name__ == "__main__":
    main()
