"""``track --overlay`` (issue 39): a video browsers play (H.264, or VP9), one frame per tracked
frame, with the tracked eyes and brows drawn where the fitted eye corners project, and a
magnified inset of the face when asked for (or when the face is small in the frame).

The speaker is the synthetic one, enrolled from its rendered video with the README's
commands (``speaker4_enrolled``); the overlay is decoded back with PyAV, independently of the
writer, and the eye positions come from the track file the same run wrote (the model's eye
corner points at each frame's tracked state, through the speaker's camera)."""

import json
import shutil

import numpy as np
import pytest

av = pytest.importorskip("av")

from articast.core.faces.scheme import mediapipe_scheme  # noqa: E402
from articast.core.faces.speaker import Speaker  # noqa: E402
from articast.core.model.camera import Pose  # noqa: E402
from articast.service.cli import main  # noqa: E402

#: MediaPipe's eye corners (outer, inner): the speaker's left eye, then the right
CORNERS = ((263, 362), (33, 133))


@pytest.fixture(scope="module")
def tracked(speaker4_enrolled, tmp_path_factory):
    d = tmp_path_factory.mktemp("overlay")
    shutil.copytree(speaker4_enrolled / "speaker", d / "speaker")
    assert main(["synth", "sequence", "-o", str(d / "clip"), "--seed", "4", "--sentence", "41",
                 "--rig", "desk", "--frames", "10", "--fps", "25"]) == 0
    runs = {}
    for name, zoom in (("plain", "off"), ("inset", "on")):
        out = d / f"{name}.mp4"
        assert main(["track", str(d / "clip" / "video.mp4"), "--speaker", str(d / "speaker"),
                     "-o", str(d / f"{name}.jsonl"), "--overlay", str(out), "--causal",
                     "--overlay-zoom", zoom, "--quiet"]) == 0
        lines = [json.loads(x) for x in (d / f"{name}.jsonl").read_text().splitlines()]
        runs[name] = (out, lines)
    return d, runs


def decode(path):
    with av.open(str(path)) as c:
        codec = c.streams.video[0].codec_context.name
        frames = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]
    return codec, frames


def eye_corners_px(speaker, line):
    """Pixel positions of each eye's (outer, inner) corner at the line's tracked state."""
    where = {int(p): i for i, p in enumerate(mediapipe_scheme(speaker.rig).points)}
    alpha = speaker.model.alpha_from_dict(line["alpha"])
    uv = speaker.camera.project_head(speaker.model.shape(alpha), Pose.from_dict(line["pose"]))
    return [(uv[where[a]], uv[where[b]]) for a, b in CORNERS]


def cyan(img):  # the eyelids' colour (BGR 255, 255, 0), after H.264's 4:2:0 chroma
    b, g, r = (img[..., i].astype(int) for i in range(3))
    return (b > 150) & (g > 150) & (r < 110)


def orange(img):  # the brows' colour (BGR 0, 140, 255)
    b, g, r = (img[..., i].astype(int) for i in range(3))
    return (r > 170) & (g > 60) & (g < 190) & (b < 90)


def test_overlay_is_a_browser_video_with_a_frame_per_tracked_frame(tracked):
    _, runs = tracked
    for out, lines in runs.values():
        codec, frames = decode(out)
        assert codec in ("h264", "vp9"), codec  # not mp4v (MPEG-4 part 2): no browser plays it
        assert len(frames) == len(lines) == 10


def test_overlay_draws_the_tracked_eyes_and_brows_at_the_eye_corners(tracked):
    d, runs = tracked
    speaker = Speaker.load(d / "speaker")
    out, lines = runs["plain"]
    _, frames = decode(out)
    seen = 0
    for img, line in zip(frames, lines, strict=True):
        if not (line["quality"]["ok"] and line.get("eyes", {}).get("ok")
                and line.get("brows", {}).get("ok")):
            continue
        seen += 1
        for outer, inner in eye_corners_px(speaker, line):
            x0, x1 = sorted((outer[0], inner[0]))
            y = 0.5 * (outer[1] + inner[1])
            width = x1 - x0
            eye = img[int(y - 0.4 * width):int(y + 0.4 * width) + 1,
                      int(x0 - 4):int(x1 + 5)]
            assert cyan(eye).sum() >= 10, (line["frame"], cyan(eye).sum())
            above = img[int(y - 1.2 * width):int(y - 0.15 * width),
                        int(x0 - 4):int(x1 + 5)]
            assert orange(above).sum() >= 10, (line["frame"], orange(above).sum())
            # and not around the mouth, far below the eyes: the lids' colour is the drawing's
            below = img[int(y + 1.5 * width):int(y + 2.5 * width), int(x0):int(x1)]
            assert cyan(below).sum() == 0
    assert seen >= 5, "too few frames with the eyes and brows tracked to check the drawing"


def test_overlay_inset_shows_the_face_in_the_corner_away_from_it(tracked):
    d, runs = tracked
    speaker = Speaker.load(d / "speaker")
    (_, plain_frames), (_, inset_frames) = (decode(runs[k][0]) for k in ("plain", "inset"))
    h, w = plain_frames[0].shape[:2]
    size = int(0.5 * min(h, w)) // 2 * 2
    (lo, li), (ro, ri) = eye_corners_px(speaker, runs["inset"][1][0])
    face_x = np.mean([lo[0], li[0], ro[0], ri[0]])
    face_y = np.mean([lo[1], li[1], ro[1], ri[1]])
    x0 = 0 if face_x > w / 2 else w - size
    y0 = 0 if face_y > h / 2 else h - size
    for plain, inset in zip(plain_frames, inset_frames, strict=True):
        # the inset holds the face with its drawn eyes where the plain overlay has none
        assert cyan(plain[y0:y0 + size, x0:x0 + size]).sum() == 0
        assert cyan(inset[y0:y0 + size, x0:x0 + size]).sum() >= 20
        # and leaves the face itself as it was drawn
        assert cyan(inset).sum() > cyan(plain).sum()
