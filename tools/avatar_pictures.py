"""The pictures of docs/AVATARS.md: the same tracked frames drawn four ways, side by side.

Rows: the synthetic speaker 4 (never a real person) rendered by its own generator with the
mouth open, closed, blinking and looking aside (and brows raised), each frame tracked live by
``LiveTracker`` with the speaker's enrolled folder, as a session tracks a camera. Columns:

1. the camera frame (the synthetic render the tracker saw, cropped to the face);
2. the avatar page (``/avatar/``) drawing the speaker's delegate at the tracked state;
3. the VRM page (``/vrm``) wearing the speaker's own VRM (``GET /api/sessions/NAME/vrm``,
   what ``articast export-vrm`` writes), driven by perfect sync;
4. the VRM page wearing a VRM of another style (``--toon``: no freely licensed stylised VRM is
   at hand offline, so :func:`toon_vrm` makes one: the same VRM writer and mesh with a flat,
   hand-painted toon texture: hair, big irises, lashes, brows, lips, blush), given to the page
   as a dropped file.

Each page is fed a replay of the tracked frame held (a ``replay-record`` session per row),
screenshotted in headless Chromium (``tests/browser.py``). Writes ``OUT/grid.jpg``.

    python tools/avatar_pictures.py --work /tmp/spk4 --out docs/avatars
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ROWS = ("mouth open", "mouth closed", "blink", "looking aside")
COLUMNS = ("camera (synthetic speaker)", "delegate (/avatar/)", "own VRM (/vrm)",
           "toon VRM (/vrm, dropped file)")
CELL = 240

# MediaPipe's 468-point mesh: outer and inner lips, eye contours, brows (upper edge)
LIPS_OUT = [61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291, 375, 321, 405, 314, 17, 84, 181,
            91, 146]
LIPS_IN = [78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 324, 318, 402, 317, 14, 87, 178,
           88, 95]
EYES = [[263, 466, 388, 387, 386, 385, 384, 398, 362, 382, 381, 380, 374, 373, 390, 249],
        [33, 246, 161, 160, 159, 158, 157, 173, 133, 155, 154, 153, 145, 144, 163, 7]]
BROWS = [[336, 296, 334, 293, 300, 276, 283, 282, 295, 285],
         [107, 66, 105, 63, 70, 46, 53, 52, 65, 55]]


def toon_texture(uv: np.ndarray, size: int = 512) -> np.ndarray:
    """A flat, hand-painted toon face (BGR) in the MediaPipe mesh's UV layout."""
    img = np.full((size, size, 3), (196, 214, 250), np.uint8)  # light peach skin
    p = (uv * size).astype(np.float32)

    def poly(ids):
        return np.round(p[ids]).astype(np.int32)

    brow_v = min(float(p[i, 1]) for b in BROWS for i in b)
    # hair: everything well above the brows, with a fringe of three locks
    img[: int(brow_v - 0.035 * size)] = (60, 70, 110)
    for cx in (0.35, 0.5, 0.65):
        cv2.ellipse(img, (int(cx * size), int(brow_v - 0.035 * size)),
                    (int(0.09 * size), int(0.045 * size)), 0, 0, 180, (60, 70, 110), -1)
    for ring in EYES:
        pts = poly(ring)
        c = pts.mean(0)
        w, h = np.ptp(pts[:, 0]), np.ptp(pts[:, 1])
        cv2.fillPoly(img, [pts], (250, 250, 250), cv2.LINE_AA)
        cv2.ellipse(img, (int(c[0]), int(c[1])), (int(0.27 * w), int(0.62 * h)), 0, 0, 360,
                    (150, 90, 40), -1, cv2.LINE_AA)  # a big blue iris
        cv2.ellipse(img, (int(c[0]), int(c[1])), (int(0.12 * w), int(0.3 * h)), 0, 0, 360,
                    (40, 20, 10), -1, cv2.LINE_AA)
        cv2.circle(img, (int(c[0] + 0.08 * w), int(c[1] - 0.2 * h)), max(2, int(0.05 * w)),
                   (255, 255, 255), -1, cv2.LINE_AA)
        cv2.polylines(img, [pts[:9]], False, (40, 30, 30), max(2, int(0.05 * w)), cv2.LINE_AA)
    for brow in BROWS:
        cv2.polylines(img, [poly(brow[:5])], False, (60, 70, 110), max(3, size // 90),
                      cv2.LINE_AA)
    cv2.fillPoly(img, [poly(LIPS_OUT)], (120, 110, 225), cv2.LINE_AA)
    cv2.fillPoly(img, [poly(LIPS_IN)], (70, 50, 140), cv2.LINE_AA)
    for side in (205, 425):  # blush on the cheeks
        c = p[side]
        blush = img.copy()
        cv2.ellipse(blush, (int(c[0]), int(c[1])), (size // 18, size // 30), 0, 0, 360,
                    (170, 170, 250), -1, cv2.LINE_AA)
        img = cv2.addWeighted(img, 0.5, blush, 0.5, 0)
    return img


def toon_vrm(speaker_dir: Path, out: Path) -> Path:
    """A stylised VRM of the speaker's mesh and model: :func:`toon_texture` on it."""
    from articast.core.delegate.build import Delegate
    from articast.core.delegate.vrm import to_vrm
    from articast.core.faces.speaker import Speaker

    speaker = Speaker.load(speaker_dir)
    d = Delegate.load(speaker_dir / "delegate.npz")
    out.write_bytes(to_vrm(speaker.model, d.mesh, toon_texture(d.mesh.uv), name="toon",
                           authors=("articast tools/avatar_pictures.py",)))
    return out


def tracked_frames(speaker_dir: Path, clip: Path) -> list[tuple[str, np.ndarray, dict]]:
    """Per row: the synthetic speaker's rendered frame and what LiveTracker made of it."""
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme
    from articast.core.faces.speaker import Speaker
    from articast.core.model.camera import Pose
    from articast.core.outputs.lips import lip_measures
    from articast.core.synthetic import default_speaker

    speaker = Speaker.load(speaker_dir)
    truth = np.load(clip / "truth.npz")
    syn = default_speaker(4)
    gap = [lip_measures(syn.model(), a)[0] for a in truth["alpha"]]
    wide, shut = int(np.argmax(gap)), int(np.argmin(gap))
    still = dict(closure_left=0.0, closure_right=0.0, gaze_yaw_deg=0.0, gaze_pitch_deg=0.0,
                 raise_left_mm=0.0, raise_right_mm=0.0)
    rows = {"mouth open": (wide, still), "mouth closed": (shut, still),
            "blink": (shut, {**still, "closure_left": 1.0, "closure_right": 1.0}),
            "looking aside": (shut, {**still, "gaze_yaw_deg": 15.0, "gaze_pitch_deg": 4.0,
                                     "raise_left_mm": 4.0, "raise_right_mm": 4.0})}
    out = []
    for name in ROWS:
        i, upper = rows[name]
        pose = Pose.from_vector(truth["poses"][i])
        image = syn.render(truth["controls"][i], pose, speaker.camera, upper=upper)
        live = LiveTracker(speaker, FaceFinder.load(threads=1), mediapipe_scheme("desk"))
        for k in range(8):  # the same frame a few times: the tracker settles on it
            r = live.track(image, k / 30)
        out.append((name, image, r.to_dict(speaker.model.param_names)))
        print(f"{name}: frame {i}, tracked ok={r.ok}, eyes {out[-1][2].get('eyes')}",
              flush=True)
    return out


def held(path: Path, speaker_dir: Path, record: dict, frames: int = 30) -> Path:
    from articast.core.faces.speaker import Speaker
    from articast.service.wire import describe

    speaker = Speaker.load(speaker_dir)
    desc = describe(speaker.model, speaker.camera, speaker.model.param_names)
    with path.open("w") as fh:
        fh.write(json.dumps({"type": "header", "format": "articast-record", "version": 1,
                             "session": "s", "source": {"kind": "test", "fps": 30}, **desc})
                 + "\n")
        for i in range(frames):
            fh.write(json.dumps({**record, "type": "frame", "seq": i, "frame": i, "t": i / 30})
                     + "\n")
    return path


def shoot(b, ready: str) -> np.ndarray:
    b.wait_for(ready, 120)
    n = b.evaluate("window.articast.rendered")
    b.wait_for(f"window.articast.rendered > {n + 3}", 60)
    time.sleep(0.3)
    return cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_COLOR)


def page_cell(img: np.ndarray, zoom: float = 1.0) -> np.ndarray:
    view = img[:, : img.shape[1] - 260]  # the page's panel is 260 px wide, on the right
    h, w = view.shape[:2]
    s = int(min(h, w) * 0.62 / zoom)
    y0, x0 = (h - s) // 2, (w - s) // 2
    return cv2.resize(view[y0:y0 + s, x0:x0 + s], (CELL, CELL), interpolation=cv2.INTER_AREA)


def box_cell(img: np.ndarray, pts: np.ndarray, margin: float = 0.12) -> np.ndarray:
    """The square around ``pts`` (screen px), grown by ``margin`` each way."""
    c = (pts.min(0) + pts.max(0)) / 2
    s = int((1 + 2 * margin) * max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1])))
    x0, y0 = int(c[0] - s / 2), int(c[1] - s / 2)
    pad = cv2.copyMakeBorder(img, s, s, s, s, cv2.BORDER_REPLICATE)
    return cv2.resize(pad[y0 + s:y0 + 2 * s, x0 + s:x0 + 2 * s], (CELL, CELL),
                      interpolation=cv2.INTER_AREA)


def camera_cell(image: np.ndarray, speaker_dir: Path, record: dict) -> np.ndarray:
    from articast.core.faces.speaker import Speaker
    from articast.core.model.camera import Pose

    sp = Speaker.load(speaker_dir)
    alpha = np.array([record["alpha"][n] for n in sp.model.param_names])
    pts = sp.camera.project_head(sp.model.shape(alpha), Pose.from_dict(record["pose"]))
    s = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]))
    # the model reaches from the chin to the eyes: the whole face, above it too
    return box_cell(image, np.vstack([pts, pts.min(0) - [0, 0.45 * s]]), 0.08)


def label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.rectangle(out, (0, 0), (out.shape[1], 18), (30, 30, 30), -1)
    cv2.putText(out, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (235, 235, 235), 1,
                cv2.LINE_AA)
    return out


def main() -> None:
    from articast.service.app import ServiceConfig
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from benchmarks.page_latency import make_speaker
    from tests.browser import Browser
    from tests.service_helpers import ServerThread

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True,
                    help="where speaker 4 is enrolled (made there if not yet)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "avatars")
    args = ap.parse_args()
    folder = make_speaker(args.work)
    args.out.mkdir(parents=True, exist_ok=True)
    frames = tracked_frames(folder, args.work / "clip")
    grid_rows = []
    with tempfile.TemporaryDirectory() as tmp:
        toon = toon_vrm(folder, Path(tmp) / "toon.vrm")
        recs = [held(Path(tmp) / f"r{i}.jsonl", folder, rec) for i, (_, _, rec) in
                enumerate(frames)]
        specs = tuple(SessionSpec(f"row{i}", f"replay-record:{r}?loop=yes", processor="truth",
                                  speaker=str(folder)) for i, r in enumerate(recs))
        config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=specs)
        with ServerThread(config) as srv:
            base = f"http://127.0.0.1:{srv.port}"
            for i, (name, image, rec) in enumerate(frames):
                cells = [camera_cell(image, folder, rec)]
                with Browser(f"{base}/avatar/?session=row{i}") as b:
                    shot = shoot(b, "window.articast.drawn === 'delegate'")
                    pts = np.array(b.evaluate("window.articast.screenPoints("
                                              "[...Array(468).keys()])"), float)
                    cells.append(box_cell(shot, pts))
                with Browser(f"{base}/vrm?session=row{i}") as b:
                    cells.append(page_cell(shoot(b, "window.articast.vrm !== ''"), 1.35))
                    doc = b.call("DOM.getDocument")
                    node = b.call("DOM.querySelector", nodeId=doc["root"]["nodeId"],
                                  selector="#file")
                    b.call("DOM.setFileInputFiles", files=[str(toon)], nodeId=node["nodeId"])
                    b.wait_for("window.articast.vrm.startsWith('toon')", 120)
                    cells.append(page_cell(shoot(b, "window.articast.vrm.startsWith('toon')"),
                                           1.35))
                grid_rows.append(np.hstack([label(c, f"{name}: {col}" if j == 0 else col)
                                            for j, (col, c) in enumerate(zip(COLUMNS, cells,
                                                                             strict=True))]))
                print(f"row {name} done", flush=True)
    grid = np.vstack(grid_rows)
    cv2.imwrite(str(args.out / "grid.jpg"), grid, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {args.out / 'grid.jpg'}")


if __name__ == "__main__":
    main()
