"""Sources and the capture thread: real video files, image folders, recordings, a missing camera."""

import time

import cv2
import numpy as np
import pytest

from articast.service.capture import Capture
from articast.service.settings import CaptureSettings
from articast.service.sources import SourceError, make_source, parse_uri, probe
from tests.service_helpers import TIMEOUT, write_recording, write_video


def drain(capture, limit=10_000):
    frames = []
    deadline = time.monotonic() + TIMEOUT
    while not capture.done and len(frames) < limit:
        assert time.monotonic() < deadline, "capture did not finish"
        f = capture.get(0.05)
        if f is not None:
            frames.append(f)
    return frames


def test_uri_parsing():
    p = parse_uri("v4l2:/dev/video2?width=640&height=480&fps=60&fourcc=MJPG")
    assert (p.kind, p.target, p.params["fps"]) == ("v4l2", "/dev/video2", "60")
    assert parse_uri("synthetic:seed=3&fps=30").params == {"seed": "3", "fps": "30"}
    for bad in ("nothing", "ftp:x", "file:a.mp4?speed=2", "v4l2:/dev/video0?fourcc=MJPEG",
                "file:a.mp4?pace=slow", "images:d?fps=abc"):
        with pytest.raises(SourceError):
            make_source(bad)


def test_fast_file_playback_is_lossless_with_container_times(tmp_path):
    levels = write_video(tmp_path / "v.avi", frames=20, fps=25)
    cap = Capture(make_source(f"file:{tmp_path / 'v.avi'}?pace=fast")).start()
    frames = drain(cap)
    cap.stop()
    assert cap.error is None and cap.dropped == 0
    assert [f.index for f in frames] == list(range(20))
    assert [f.t for f in frames] == pytest.approx([i / 25 for i in range(20)])
    means = [float(f.image[:, 40:, 1].mean()) for f in frames]
    assert means == pytest.approx(levels, abs=3)  # MJPG is lossy
    assert all(b >= a for a, b in zip([f.t_capture for f in frames][:-1],
                                      [f.t_capture for f in frames][1:], strict=True))
    assert cap.info.width == 64 and cap.info.height == 48 and cap.info.fps == 25


def test_plays_continue_the_time_line(tmp_path):
    write_video(tmp_path / "v.avi", frames=5, fps=10)
    cap = Capture(make_source(f"file:{tmp_path / 'v.avi'}?pace=fast&plays=3")).start()
    frames = drain(cap)
    assert [f.index for f in frames] == list(range(15))
    ts = [f.t for f in frames]
    assert ts == pytest.approx([i / 10 for i in range(15)])


def test_a_part_of_a_file_start_and_end(tmp_path):
    """file:...?start=SECONDS&end=FRAMESf plays that part exactly; looping it continues the
    time line from the part's own start."""
    write_video(tmp_path / "v.avi", frames=20, fps=25)
    v = tmp_path / "v.avi"
    cap = Capture(make_source(f"file:{v}?pace=fast&start=0.2&end=15f&plays=2")).start()
    frames = drain(cap)
    assert cap.error is None
    assert len(frames) == 20 and cap.info.frame_count == 10
    assert [f.t for f in frames] == pytest.approx([0.2 + i / 25 for i in range(20)])
    assert "0.2 s to 15f" in cap.info.detail["span"]
    for bad in ("start=x", "start=5f&end=2f", "end=-1"):
        with pytest.raises(SourceError):
            make_source(f"file:{v}?{bad}")
    cap = Capture(make_source(f"file:{v}?start=30")).start()
    drain(cap)
    assert isinstance(cap.error, SourceError) and "no frame from 30 s" in str(cap.error)


def test_loop_means_what_it_says(tmp_path):
    """serve --help's own example, loop=1, played the file once (loop was a count of plays):
    loop is a switch now, plays=N the count, and a count given to loop is one clear error."""
    write_video(tmp_path / "v.avi", frames=5, fps=10)
    v = tmp_path / "v.avi"
    for value in ("1", "yes", "true", "on", "forever"):
        assert make_source(f"file:{v}?loop={value}").loops == 0  # forever
    for value in ("0", "no", "false", "off"):
        assert make_source(f"file:{v}?loop={value}").loops == 1  # once
    assert make_source(f"file:{v}").loops == 1
    cap = Capture(make_source(f"file:{v}?pace=fast&loop=1")).start()
    frames = drain(cap, limit=12)  # more than one play of 5 frames, and still going
    cap.stop()
    assert [f.index for f in frames] == list(range(12))
    for bad, says in (("loop=3", "plays=N"), ("loop=yes&plays=2", "plays=2"),
                      ("plays=0", ">= 1")):
        with pytest.raises(SourceError, match=says):
            make_source(f"file:{v}?{bad}")


def test_realtime_pace_follows_media_time_and_keeps_the_newest(tmp_path):
    write_video(tmp_path / "v.avi", frames=10, fps=20)  # 0.45 s of media
    cap = Capture(make_source(f"file:{tmp_path / 'v.avi'}")).start()
    first = cap.get(TIMEOUT)  # playback starts when its first frame is wanted
    t0 = time.monotonic()
    time.sleep(0.7)  # a tracker that never came back: frames are replaced, not queued
    last = cap.get(TIMEOUT)
    assert time.monotonic() - t0 >= 0.4
    assert first is not None and first.index == 0
    assert last is not None and last.index == 9
    assert cap.dropped == 8


def test_corrupt_file_gives_one_clear_error(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00\x01garbage" * 500)
    with pytest.raises(SourceError, match="bad.mp4"):
        probe(f"file:{bad}")
    statuses = []
    cap = Capture(make_source(f"file:{bad}"), on_status=lambda s, d: statuses.append(s)).start()
    drain(cap)
    assert isinstance(cap.error, SourceError) and "bad.mp4" in str(cap.error)
    assert "unavailable" not in statuses  # not retried
    with pytest.raises(SourceError, match="no such file"):
        probe(f"file:{tmp_path / 'missing.mp4'}")


def test_image_folder(tmp_path):
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), np.full((8, 10, 3), 50 * i, np.uint8))
    (tmp_path / "notes.txt").write_text("ignored")
    cap = Capture(make_source(f"images:{tmp_path}?fps=10&pace=fast")).start()
    frames = drain(cap)
    assert [int(f.image.mean()) for f in frames] == [0, 50, 100, 150]
    assert [f.t for f in frames] == pytest.approx([0, 0.1, 0.2, 0.3])


def test_unreadable_image_and_empty_folder(tmp_path):
    with pytest.raises(SourceError, match="no images"):
        probe(f"images:{tmp_path}")
    (tmp_path / "a.png").write_bytes(b"not a png")
    with pytest.raises(SourceError, match="a.png: not a readable image"):
        probe(f"images:{tmp_path}")


def test_recording_replays_ground_truth(tmp_path):
    rec = tmp_path / "r.jsonl"
    truth = write_recording(rec, frames=12)
    with rec.open("a") as fh:
        fh.write('{"type": "frame", "fra')  # a crash mid-line: the frame in flight is lost
    src = make_source(f"replay-record:{rec}?pace=fast")
    cap = Capture(src).start()
    frames = drain(cap)
    assert cap.error is None
    assert len(frames) == 12 and all(f.image is None for f in frames)
    for f, r in zip(frames, truth, strict=True):
        np.testing.assert_allclose(f.truth.alpha, r.alpha)
        np.testing.assert_allclose(f.truth.pose.translation, r.pose.translation)
    assert cap.assets.model is not None and cap.assets.model.n_points == 12


def test_malformed_recording_line_is_an_error(tmp_path):
    rec = tmp_path / "r.jsonl"
    write_recording(rec, frames=3)
    lines = rec.read_text().splitlines(keepends=True)
    lines.insert(2, "this is not json\n")
    rec.write_text("".join(lines))
    cap = Capture(make_source(f"replay-record:{rec}?pace=fast")).start()
    drain(cap)
    assert isinstance(cap.error, SourceError) and ":3:" in str(cap.error)


def test_missing_camera_is_a_status_with_retries_not_a_crash():
    statuses = []
    settings = CaptureSettings(retry_initial_s=0.02, retry_max_s=0.05)
    cap = Capture(make_source("v4l2:/dev/video97?width=640"), settings,
                  on_status=lambda s, d: statuses.append((s, d))).start()
    deadline = time.monotonic() + TIMEOUT
    while cap.attempts < 3:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    cap.stop()
    assert cap.error is None and cap.info is None
    assert statuses and all(s == "unavailable" for s, _ in statuses)
    assert "/dev/video97" in statuses[0][1] and "retry" in statuses[0][1]


def test_synthetic_source_brings_model_camera_appearance_and_truth(tmp_path, monkeypatch):
    """... and its first open says what it builds (the first `articast demo` looked hung),
    once: the next open loads the cache. probe() (serve's check before starting) does not
    build it in the server's own process any more."""
    from articast.service.sources import make_source

    monkeypatch.setenv("ARTICAST_CACHE_DIR", str(tmp_path / "cache"))
    assert probe("synthetic:seed=0&fps=30").kind == "synthetic"
    assert not (tmp_path / "cache").exists()
    said = []
    src = make_source("synthetic:seed=0&fps=30")
    src.progress = said.append
    src.open()
    src.close()
    assert len(said) == 1 and said[0].startswith("building synthetic speaker 0's model")
    assert str(tmp_path / "cache") in said[0]
    src = make_source("synthetic:seed=0&fps=30")
    src.progress = said.append
    info = src.open()
    assert len(said) == 1
    try:
        assets = src.assets()
        assert (info.width, info.height) == (640, 480) and info.kind == "synthetic"
        assert assets.model is not None and assets.appearance is not None
        assert assets.extra["rig"] == "head" and assets.extra["initial_pose"] is not None
        t0, img, truth = src.read()
        t1, _, truth1 = src.read()
        assert img.shape == (480, 640, 3) and img.dtype == np.uint8
        assert t1 - t0 == pytest.approx(1 / 30)
        assert truth.alpha.shape == (7,) and truth1.frame == truth.frame + 1
    finally:
        src.close()


class FlakyCamera:
    """A fake device (not our code): delivers 5 frames, is unplugged, is missing for 2 opens."""

    live, pace, loops, uri = True, "realtime", 1, "fake:camera"

    def __init__(self):
        self.opens = 0
        self.reads = 0

    def open(self):
        from articast.service.sources import SourceInfo, SourceUnavailable

        self.opens += 1
        if 2 <= self.opens <= 3:
            raise SourceUnavailable("fake:camera: no such device")
        self.reads = 0
        return SourceInfo(self.uri, "fake", True, 8, 6, 100.0)

    def read(self):
        from articast.service.sources import SourceUnavailable

        self.reads += 1
        if self.opens == 1 and self.reads > 5:
            raise SourceUnavailable("fake:camera: stopped delivering frames (unplugged?)")
        time.sleep(0.005)
        return self.reads * 0.01, np.zeros((6, 8, 3), np.uint8), None

    def close(self):
        pass

    def assets(self):
        from articast.service.sources import SourceAssets

        return SourceAssets()


def test_an_unplugged_camera_is_reopened_with_backoff():
    statuses = []
    cam = FlakyCamera()
    cap = Capture(cam, CaptureSettings(retry_initial_s=0.01, retry_max_s=0.02),
                  on_status=lambda s, d: statuses.append((s, d))).start()
    frames = []
    deadline = time.monotonic() + TIMEOUT
    while len(frames) < 15:
        assert time.monotonic() < deadline
        f = cap.get(0.05)
        if f is not None:
            frames.append(f)
    cap.stop()
    states = [s for s, _ in statuses]
    assert states[0] == "running"
    assert states.count("unavailable") == 3  # lost, then 2 failed reopen attempts
    assert ("running", "source is back") in statuses
    assert cam.opens == 4 and cap.error is None
    assert [f.index for f in frames] == sorted(f.index for f in frames)  # one time line


def test_a_session_added_over_http_is_told_what_its_file_is(tmp_path):
    """check_uri (POST /api/sessions) said "no such file" for a FIFO, /dev/zero or a folder
    that is there (issue 39); it says what the path is, from its status alone (the worker
    opens and reads it: a text file fails that session once, as a corrupt one does)."""
    import os

    from articast.service.sources import check_uri

    fifo = tmp_path / "fifo.mp4"
    os.mkfifo(fifo)
    (tmp_path / "folder.mp4").mkdir()
    notes = tmp_path / "notes.txt"
    notes.write_text("not a video\n")
    for uri, says in ((f"file:{fifo}", "is a FIFO"), ("file:/dev/zero", "is a device"),
                      (f"file:{tmp_path / 'folder.mp4'}", "is a folder"),
                      (f"replay-record:{fifo}", "is a FIFO"),
                      (f"file:{tmp_path / 'gone.mp4'}", "no such file"),
                      (f"images:{notes}", "not a folder")):
        with pytest.raises(SourceError, match=says):
            check_uri(uri)
    check_uri(f"file:{notes}")  # there and regular: the worker reads it
    with pytest.raises(SourceError, match="a text file, not a video"):
        probe(f"file:{notes}")


def test_a_symlink_loop_is_named_a_loop(tmp_path, capsys):
    """Issue 39: a link that leads back to itself said "cannot open it (Too many levels of
    symbolic links)" from serve and replay-record; one line now names it a link loop, from
    the URI check (POST /api/sessions) and from the commands, exit 2, no traceback."""
    import os

    from articast.service.cli import main
    from articast.service.sources import check_uri

    loop = tmp_path / "loop.mp4"
    os.symlink(loop.name, loop)  # loop.mp4 -> loop.mp4
    for uri in (f"file:{loop}", f"replay-record:{loop}"):
        with pytest.raises(SourceError, match="loop.mp4: a symbolic link loop"):
            check_uri(uri)
    for args in (["serve", "--source", f"x=file:{loop}", "--port", "0"],
                 ["replay-record", str(loop), "--port", "0"]):
        assert main(args) == 2
        out, err = capsys.readouterr()
        lines = [x for x in err.splitlines() if x.strip()]
        assert len(lines) == 1 and "loop.mp4: a symbolic link loop" in lines[0], err
        assert "Traceback" not in err and not out.strip()
