"""The speaker's own delegate shuts its eyes on a blink and looks where the stream says
(issue 40: "lids that close on a blink and irises that follow the gaze, not overlays").

Headless Chromium, the avatar page drawing the synthetic speaker 4's delegate (enrolled from its
rendered video), four sessions of the same held face differing only in the `eyes` block:
open looking ahead, shut (closure 1), open looking 30 deg to either side. Each eye's region is
its lid contour as the page drew it open (the page's ``screenPoints`` hook: where the
delegate's vertices are on screen). Checked from the screenshots:

* open, the region shows the eye: a good part of it is the eye's own colours (the sclera's
  bright, unsaturated white and the iris's and pupil's dark), measured against the skin
  around it;
* shut, none of those colours are left in the region (the old page squashed the painted eye
  into a slit: its sclera and iris still showed), and there is no hole: the region is covered
  by the face (no background colour);
* looking aside, the iris (the dark part of the region) sits towards that side, by more
  than a pixel, each way.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.browser import CHROMIUM

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed "
                                "(.ci/run installs Debian's chromium)")

# MediaPipe's face mesh: each eye's lid contour, in order around it (the speaker's left first)
RINGS = [[263, 466, 388, 387, 386, 385, 384, 398, 362, 382, 381, 380, 374, 373, 390, 249],
         [33, 246, 161, 160, 159, 158, 157, 173, 133, 155, 154, 153, 145, 144, 163, 7]]


def _held(path: Path, speaker, eyes: dict, frames: int = 30) -> Path:
    """A replayable recording of the speaker's neutral face, face-on, holding ``eyes``."""
    from articast.service.wire import describe

    model = speaker.model
    desc = describe(model, speaker.camera, model.param_names)
    pose = {"rotation": [3.14159, 0.0, 0.0], "translation": [0.0, 0.0, 450.0]}
    block = {"ok": True, "reason": "", "closure_left": 0.0, "closure_right": 0.0,
             "gaze_yaw_deg": 0.0, "gaze_pitch_deg": 0.0, "wide_left": 0.0, "wide_right": 0.0,
             "lower_lid_left": 0.0, "lower_lid_right": 0.0, **eyes}
    brows = {"ok": True, "reason": "", "raise_left_mm": 0.0, "raise_right_mm": 0.0,
             "raise_inner_left_mm": 0.0, "raise_outer_left_mm": 0.0, "raise_inner_right_mm": 0.0,
             "raise_outer_right_mm": 0.0, "lowering_mm": 0.0, "squeeze_left_mm": 0.0,
             "squeeze_right_mm": 0.0}
    with path.open("w") as fh:
        fh.write(json.dumps({"type": "header", "format": "articast-record", "version": 1,
                             "session": "s", "source": {"kind": "test", "fps": 30}, **desc})
                 + "\n")
        for i in range(frames):
            fh.write(json.dumps({"type": "frame", "seq": i, "frame": i, "t": i / 30,
                                 "alpha": {n: 0.0 for n in model.param_names}, "pose": pose,
                                 "eyes": block, "brows": brows,
                                 "quality": {"ok": True, "reason": "", "residual": 0.0,
                                             "evals": 0, "iterations": 0, "ms": 0.0}}) + "\n")
    return path


STATES = {"open": {}, "shut": {"closure_left": 1.0, "closure_right": 1.0},
          "left": {"gaze_yaw_deg": 30.0}, "right": {"gaze_yaw_deg": -30.0}}


def eye_shots(folder: Path, tmp: Path, states: dict = STATES) -> tuple[dict, list]:
    """Per state a screenshot (BGR) of the avatar page drawing the delegate of the speaker
    folder; the eye contours (screen px) as drawn in the first state."""
    from articast.core.faces.speaker import Speaker
    from articast.service.app import ServiceConfig
    from articast.service.settings import ServerSettings
    from articast.service.worker import SessionSpec
    from tests.browser import Browser
    from tests.service_helpers import ServerThread

    speaker = Speaker.load(folder)
    specs = tuple(SessionSpec(name, f"replay-record:{_held(tmp / f'{name}.jsonl', speaker, e)}"
                              "?loop=yes", processor="truth", speaker=str(folder))
                  for name, e in states.items())
    config = ServiceConfig(server=ServerSettings(log_level="critical"), sessions=specs)
    shots, rings = {}, None
    with ServerThread(config) as srv:
        for name in states:
            with Browser(f"http://127.0.0.1:{srv.port}/avatar/?session={name}") as b:
                b.wait_for("window.articast.delegate.startsWith('textured')", 90)
                b.wait_for("window.articast.drawn === 'delegate'", 60)
                n = b.evaluate("window.articast.rendered")
                b.wait_for(f"window.articast.rendered > {n + 3}", 60)
                if rings is None:
                    rings = [np.array(b.evaluate(f"window.articast.screenPoints({r})"), float)
                             for r in RINGS]
                png = b.screenshot()
            shots[name] = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return shots, rings


def _region(shape, ring):
    mask = np.zeros(shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(ring).astype(np.int32)], 1)
    return mask > 0


def eye_colours(img, ring):
    """Of the eye's region, the fraction that is the eye's own colours: sclera (bright, little
    saturation) or iris and pupil (darker than the skin around the eye by far); and the
    dark part's mask."""
    inside = _region(img.shape, ring)
    grown = cv2.dilate(inside.astype(np.uint8), np.ones((25, 25), np.uint8)) > 0
    around = grown & ~(cv2.dilate(inside.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV).astype(float)
    skin_v = np.median(hsv[..., 2][around])
    skin_s = np.median(hsv[..., 1][around])
    sclera = (hsv[..., 1] < 0.55 * skin_s) & (hsv[..., 2] > 0.85 * skin_v)
    dark = hsv[..., 2] < 0.55 * skin_v
    return float(((sclera | dark) & inside).sum() / max(inside.sum(), 1)), dark & inside


def test_the_delegates_lids_shut_on_a_blink_and_its_irises_follow_the_gaze(
        speaker4_enrolled, tmp_path):
    shots, rings = eye_shots(speaker4_enrolled / "speaker", tmp_path)
    out = Path(os.environ.get("ARTICAST_TEST_ARTEFACTS") or tmp_path)
    out.mkdir(parents=True, exist_ok=True)
    for name, img in shots.items():
        cv2.imwrite(str(out / f"delegate-eyes-{name}.png"), img)
    background = shots["open"][5, 5].astype(int)
    for side, ring in zip(("left", "right"), rings, strict=True):
        assert _region(shots["open"].shape, ring).sum() > 40, side  # an eye of some size
        opened, _ = eye_colours(shots["open"], ring)
        shut, _ = eye_colours(shots["shut"], ring)
        print(f"{side} eye: eye colours open {opened:.2f}, shut {shut:.3f}")
        assert opened > 0.3, (side, opened)  # the open eye shows its sclera and iris
        assert shut < 0.03, (side, shut)  # shut: none of it (the old page: a slit)
        inside = _region(shots["shut"].shape, ring)
        hole = (np.abs(shots["shut"].astype(int) - background).sum(2) < 12) & inside
        assert hole.sum() == 0, side  # covered by the face, no background showing
        # the iris looks aside: the dark part's middle moves the gaze's way on screen (the
        # speaker's left is the viewer's right: +x on the screen)
        xs = {}
        for look in ("left", "right"):
            _, dark = eye_colours(shots[look], ring)
            assert dark.sum() > 5, (side, look)
            xs[look] = float(np.nonzero(dark)[1].mean())
        print(f"{side} eye: iris x looking left {xs['left']:.1f}, right {xs['right']:.1f}")
        assert xs["left"] > xs["right"] + 1.0, (side, xs)
