"""Render docs/scan_jaw_closed.png, docs/scan_jaw_open.png and the same turned 35 degrees
(docs/scan_jaw_closed_turned.png, docs/scan_jaw_open_turned.png): menpo3d's james, bound to
the synthetic speaker by its landmarks, textured, in the browser avatar (real headless
Chromium) animated by streams of the speaker, jaw1 = 0 and jaw1 at the top of its training
range, the head frontal or turned (the stream's head pose, relative to its first frame).

    python tools/fetch_scan.py
    python docs/make_scan_screenshots.py [--scan DIR] [--output-dir docs]
"""

from __future__ import annotations

import argparse
import json
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

FRAMES, FRONTAL = 300, 60


def recording(path: Path, jaw1: float, yaw: float, frames: int = FRAMES) -> Path:
    """The speaker holding jaw1, its head turned by ``yaw`` rad after 2 s frontal (the server
    takes the first frame it has the description for as the neutral pose)."""
    from scipy.spatial.transform import Rotation

    from articast.core.model.camera import Camera
    from articast.core.synthetic import rest_pose
    from articast.service.wire import describe

    model = default_speaker(0).model()
    desc = describe(model, Camera.default(640, 480), model.param_names)
    rest = rest_pose("head").to_dict()
    turned = dict(rest, rotation=(Rotation.from_rotvec(rest["rotation"])
                                  * Rotation.from_rotvec([0.0, yaw, 0.0])).as_rotvec().tolist())
    with path.open("w") as fh:
        fh.write(json.dumps({"type": "header", "format": "articast-record", "version": 1,
                             "session": "s", "source": {"kind": "test", "fps": 30},
                             **desc}) + "\n")
        for i in range(frames):
            alpha = {n: 0.0 for n in model.param_names}
            alpha["jaw1"] = jaw1
            fh.write(json.dumps({"type": "frame", "seq": i, "frame": i, "t": i / 30,
                                 "alpha": alpha, "pose": rest if i < FRONTAL else turned,
                                 "quality": {"ok": True, "reason": "", "residual": 0.0,
                                             "evals": 0, "iterations": 0, "ms": 0.0}}) + "\n")
    return path


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
        shots = {"closed": (0.0, 0.0), "open": (jaw_open, 0.0),
                 "closed_turned": (0.0, 0.6), "open_turned": (jaw_open, 0.6)}
        sessions = tuple(SessionSpec(name, f"replay-record:{recording(d / f'{name}.jsonl', *v)}"
                                           "?loop=yes") for name, v in shots.items())
        config = ServiceConfig(server=ServerSettings(log_level="critical",
                                                     scan=str(d / "james.npz")),
                               sessions=sessions)
        with ServerThread(config) as srv:
            for name, (jaw1, _) in shots.items():
                with Browser(f"http://127.0.0.1:{srv.port}/avatar/?session={name}") as b:
                    b.wait_for("window.articast.mesh.startsWith('scan')", 90)
                    b.wait_for(f"window.articast.lastSeq % {FRAMES} >= {FRONTAL + 30}", 30)
                    b.wait_for(f"window.articast.rendered > "
                               f"{b.evaluate('window.articast.rendered') + 5}", 30)
                    time.sleep(0.3)
                    png = b.screenshot()
                img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
                out = args.output_dir / f"scan_jaw_{name}.png"
                cv2.imwrite(str(out), img[:, 100: img.shape[1] - 360])  # the head, not the panel
                print(f"{out}  jaw1 = {jaw1:.2f}")


if __name__ == "__main__":
    main()
