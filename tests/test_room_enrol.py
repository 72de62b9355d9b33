"""The room's enrolment from the page (issue 41 item 2; service/room_enrol.py): the upload's
checks, the token rules (a participant token enrols and deletes only its own name), one
enrolment per participant and one in the room at a time, and what happens to an upload cut off
or an enrolment whose page went away: stopped, its files removed. The enrolment itself, from a
real browser's recording, is in tests/test_room.py's two-browser test."""

import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from articast.core import enrol_upload as U
from tests.service_helpers import TIMEOUT, ServerThread

pytest.importorskip("aiortc", reason="the room needs aiortc (the test extra installs it)")

from articast.service.room import participant_token  # noqa: E402
from tests.test_room import ROOM, config, http, join, room_of  # noqa: E402

EBML = b"\x1a\x45\xdf\xa3"


def write_webm(path, seconds, fps=5, size=(160, 120)):
    """A VP8 WebM as a browser records it: frames of noise (no face), ``seconds`` long."""
    import av

    rng = np.random.default_rng(0)
    with av.open(str(path), "w", format="webm") as box:
        st = box.add_stream("libvpx", rate=fps)
        st.width, st.height, st.pix_fmt = size[0], size[1], "yuv420p"
        st.options = {"deadline": "realtime", "cpu-used": "8"}
        for _ in range(int(seconds * fps)):
            img = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
            for packet in st.encode(av.VideoFrame.from_ndarray(img, format="bgr24")):
                box.mux(packet)
        for packet in st.encode():
            box.mux(packet)
    return path


@pytest.fixture(scope="module")
def webms(tmp_path_factory):
    d = tmp_path_factory.mktemp("webm")
    return {"short": write_webm(d / "short.webm", 5), "long": write_webm(d / "long.webm", 20)}


def headers(name, kind="video/webm;codecs=vp8"):
    return {"X-Participant-Token": participant_token(ROOM, name), "Content-Type": kind}


def work_files(root):
    """What the room's temporary folders hold (nothing once an enrolment ended)."""
    work = root / ".enrolling"
    return sorted(str(p.relative_to(work)) for p in work.rglob("*")) if work.exists() else []


def wait(predicate, timeout=6 * TIMEOUT, what=""):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


# ----------------------------------------------------------------------------- pure checks
def test_the_upload_checks_refuse_what_is_not_a_camera_clip_in_one_line():
    assert U.upload_problem("video/webm;codecs=vp8", "1000") == (0, "")
    assert U.upload_problem("video/mp4", None) == (0, "")
    status, line = U.upload_problem("text/html", "10")
    assert status == 415 and "text/html" in line and "\n" not in line
    assert U.upload_problem("", "10")[0] == 415
    assert U.upload_problem("video/webm", str(U.MAX_UPLOAD_BYTES + 1))[0] == 413
    assert U.upload_problem("video/webm", "12x")[0] == 400
    assert U.upload_problem("video/webm", "0") == (400, "the clip is empty")
    # the first bytes must be the container the type names
    assert U.container_problem("video/webm", EBML + b"\x00" * 12) == ""
    assert U.container_problem("video/mp4", b"\x00\x00\x00\x18ftypmp42") == ""
    assert "not a webm" in U.container_problem("video/webm", b"<html><body>")
    assert U.container_problem("video/mp4", EBML + b"\x00" * 12) != ""
    assert U.container_problem("video/webm", b"") != ""
    # a decoded clip: long enough, not huge, with frames
    assert U.clip_problem(24.0, 720, 640, 480) == ""
    assert "5.0 s long" in U.clip_problem(5.0, 150, 640, 480)
    assert "s long" in U.clip_problem(float("nan"), 150, 640, 480)
    assert "no video frame" in U.clip_problem(24.0, 0, 0, 0)
    assert "3840x2160" in U.clip_problem(24.0, 720, 3840, 2160)
    assert "at most 90" in U.clip_problem(200.0, 720, 640, 480)
    # the progress only grows through the stages, to 1 when done
    seq = [U.overall(s, d, n) for s, d, n in (("upload", 0, 0), ("decoding", 0, 0),
                                               ("landmarks", 50, 100), ("landmarks", 100, 100),
                                               ("reader landmarks", 10, 100), ("model", 3, 6),
                                               ("delegate", 0, 0), ("done", 0, 0))]
    assert seq == sorted(seq) and seq[-1] == 1.0 and len(set(seq)) == len(seq)
    assert U.overall("no such stage") == 0.0


# ----------------------------------------------------------------------------- tokens
def test_a_participant_token_enrols_and_deletes_only_its_own_name(tmp_path, webms):
    for name in ("ann", "bob"):  # two enrolled folders (made by the host)
        (tmp_path / name).mkdir()
        (tmp_path / name / "speaker.json").write_text("{}")
    clip = webms["short"].read_bytes()
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        bob = headers("bob")
        for method, path in (("POST", "/room/api/enrol/ann"), ("GET", "/room/api/enrol/ann"),
                             ("DELETE", "/room/api/enrol/ann"),
                             ("POST", "/room/api/enrol/ann/cancel")):
            r = c.request(method, path, headers=bob, content=clip if method == "POST" else None)
            assert r.status_code == 403, (method, path, r.text)
            assert "only its own name" in r.json()["detail"]
        # a token bob made up for ann (his MAC, her name), or none, opens nothing
        forged = {**bob, "X-Participant-Token": "ann." + bob["X-Participant-Token"].split(".")[1]}
        for h in (forged, {"Content-Type": "video/webm"}):
            assert c.delete("/room/api/enrol/ann", headers=h).status_code == 401
            assert c.post("/room/api/enrol/ann", headers=h, content=clip).status_code == 401
        # the room token is no participant token
        assert c.delete("/room/api/enrol/ann",
                        headers={"X-Participant-Token": ROOM}).status_code == 401
        assert (tmp_path / "ann" / "speaker.json").is_file()
        # bob deletes his own: the folder is gone, his name can be joined with the room token
        assert join(c, "bob").status_code == 403
        r = c.delete("/room/api/enrol/bob", headers=bob)
        assert r.status_code == 200 and r.json() == {"name": "bob", "deleted": True,
                                                     "enrolled": False}
        assert not (tmp_path / "bob").exists() and (tmp_path / "ann").is_dir()
        assert c.get("/room/api/enrol/bob", headers=bob).json()["enrolled"] is False
        assert join(c, "bob").status_code == 200
        assert c.delete("/room/api/enrol/bob", headers=bob).json()["deleted"] is False
        # a name that is not a folder's (the room's own temporary folders are hidden ones)
        h = headers(".enrolling")
        r = c.delete("/room/api/enrol/.enrolling", headers=h)
        assert r.status_code == 200 and r.json()["deleted"] is False
        assert c.post("/room/api/enrol/.enrolling", headers=h, content=clip).status_code == 400
    # a name the page enrolled has a token bound to its folder's secret (room-key): the
    # token anyone could take for the name before no longer admits; the host's command
    # mints the bound one from the folder
    (tmp_path / "cleo").mkdir()
    (tmp_path / "cleo" / "speaker.json").write_text("{}")
    (tmp_path / "cleo" / "room-key").write_text("s3cret\n")
    out = subprocess.run([sys.executable, "-m", "articast.service.cli", "room-token", "cleo",
                          "--speakers", str(tmp_path)], capture_output=True, text=True,
                         env={"ARTICAST_ROOM_TOKEN": ROOM, "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    bound = out.stdout.split()[0]
    assert bound == participant_token(ROOM, "cleo", "s3cret") != participant_token(ROOM, "cleo")
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        assert c.get("/room/api/me", headers={"X-Participant-Token": bound}).status_code == 200
        assert c.get("/room/api/me", headers=headers("cleo")).status_code == 401
        assert c.delete("/room/api/enrol/cleo", headers=headers("cleo")).status_code == 401
        assert (tmp_path / "cleo").is_dir()
    # without a speakers folder there is nothing to enrol into
    with ServerThread(config()) as srv, http(srv) as c:
        r = c.post("/room/api/enrol/bob", headers=headers("bob"), content=clip)
        assert r.status_code == 404 and "--speakers" in r.json()["detail"]


# ----------------------------------------------------------------------------- uploads
def enrol(c, name, body, kind="video/webm;codecs=vp8"):
    return c.post(f"/room/api/enrol/{name}", headers=headers(name, kind), content=body)


def status(c, name):
    return c.get(f"/room/api/enrol/{name}", headers=headers(name)).json()


def finished(c, name):
    wait(lambda: status(c, name)["job"]["state"] not in ("uploading", "running"),
         what=f"{name}'s enrolment did not end")
    return status(c, name)["job"]


def test_hostile_and_unusable_uploads_are_one_line_and_leave_no_file(tmp_path, webms):
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        # refused before the decoder sees a byte
        cases = [("text/plain", b"hello", 415, "camera recording"),
                 ("video/webm", b"<html>" + b"x" * 100, 415, "not a webm"),
                 ("video/webm", b"", 400, "empty"),
                 ("video/webm", EBML, 400, "4 bytes")]
        for kind, body, code, says in cases:
            r = enrol(c, "ann", body, kind)
            assert r.status_code == code, (kind, r.text)
            assert says in r.json()["detail"] and "\n" not in r.json()["detail"]
            assert work_files(tmp_path) == []
        s = partial_upload(srv, "ann", sent=4, declared=2**30)  # a 1 GB clip, declared
        try:
            s.settimeout(TIMEOUT)
            assert s.recv(100).startswith(b"HTTP/1.1 413")
        finally:
            s.close()
        # a WebM header on bytes that are no video: the decoder's verdict, in one line
        r = enrol(c, "ann", EBML + os.urandom(4000))
        assert r.status_code == 202, r.text
        job = finished(c, "ann")
        assert job["state"] == "failed" and "\n" not in job["detail"], job
        assert "cannot be read as video" in job["detail"] or "no video" in job["detail"], job
        # a real clip, too short
        assert enrol(c, "ann", webms["short"].read_bytes()).status_code == 202
        job = finished(c, "ann")
        assert job["state"] == "failed" and "5.0 s long" in job["detail"], job
        # long enough, but no face in it
        assert enrol(c, "ann", webms["long"].read_bytes()).status_code == 202
        job = finished(c, "ann")
        assert job["state"] == "failed" and "a face was found in 0 of" in job["detail"], job
        assert "Traceback" not in job["detail"] and "\n" not in job["detail"]
        assert not (tmp_path / "ann").exists() and work_files(tmp_path) == []


def partial_upload(srv, name, sent=4096, declared=1_000_000):
    """An upload that stops half-way (a page closed mid-upload): the open socket."""
    s = socket.create_connection(("127.0.0.1", srv.port))
    s.sendall((f"POST /room/api/enrol/{name} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
               f"X-Participant-Token: {participant_token(ROOM, name)}\r\n"
               f"Content-Type: video/webm\r\nContent-Length: {declared}\r\n\r\n").encode()
              + EBML + b"\x00" * (sent - 4))
    return s


def test_one_enrolment_per_participant_one_in_the_room_and_a_cut_upload_leaves_nothing(
        tmp_path, webms):
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        jobs = room_of(srv).enrolments.jobs
        s = partial_upload(srv, "ann")
        try:
            wait(lambda: "ann" in jobs and (tmp_path / ".enrolling").exists() and
                 work_files(tmp_path), what="ann's upload did not begin")
            assert jobs["ann"].state == "uploading"
            r = enrol(c, "ann", webms["long"].read_bytes())
            assert r.status_code == 429 and "already under way" in r.json()["detail"]
            r = enrol(c, "bob", webms["long"].read_bytes())
            assert r.status_code == 429 and "at most 1 at once" in r.json()["detail"], r.text
        finally:
            s.close()  # the page went away mid-upload
        wait(lambda: jobs["ann"].state == "cancelled", what="the cut upload was not cancelled")
        assert "cut off" in jobs["ann"].detail
        wait(lambda: work_files(tmp_path) == [], what=str(work_files(tmp_path)))
        # the room is free again: bob's turn
        assert enrol(c, "bob", webms["short"].read_bytes()).status_code == 202
        assert finished(c, "bob")["state"] == "failed"


def test_an_enrolment_whose_page_stopped_asking_or_cancelled_is_killed_and_removed(
        tmp_path, webms):
    """The enrolment process runs until its page stops asking how it goes (lease) or
    cancels: then it is killed and its temporary folder removed."""
    from dataclasses import replace

    clip = webms["long"].read_bytes()
    with ServerThread(config(speakers=str(tmp_path))) as srv, http(srv) as c:
        jobs = room_of(srv).enrolments.jobs
        # the page cancels (its cancel button, or closing: pagehide)
        r = enrol(c, "ann", clip)
        assert r.status_code == 202
        assert jobs["ann"].proc is not None and jobs["ann"].exitcode is None and \
            jobs["ann"].state == "running"
        # the upload's answer is ann's token once enrolled; while it runs both admit
        bound = {"X-Participant-Token": r.json()["token"]}
        assert bound["X-Participant-Token"] != headers("ann")["X-Participant-Token"]
        assert c.get("/room/api/enrol/ann", headers=bound).status_code == 200
        r = c.post("/room/api/enrol/ann/cancel", headers=headers("ann"))
        assert r.json()["job"]["state"] == "cancelled", r.text
        # cancelled: the bound token is void, the name's own still admits
        assert c.get("/room/api/enrol/ann", headers=bound).status_code == 401
        assert c.get("/room/api/enrol/ann", headers=headers("ann")).status_code == 200
        wait(lambda: jobs["ann"].exitcode is not None, what="the enrolment process lives on")
        assert jobs["ann"].exitcode == -9  # killed (read by the service's own reader thread)
        wait(lambda: work_files(tmp_path) == [], what=str(work_files(tmp_path)))
    # the page stops asking (closed without a word): cancelled after the lease (here 50 ms)
    cfg = config(speakers=str(tmp_path))
    cfg = replace(cfg, room=replace(cfg.room, enrol_lease_s=0.05))
    with ServerThread(cfg) as srv, http(srv) as c:
        jobs = room_of(srv).enrolments.jobs
        assert enrol(c, "bob", clip).status_code == 202
        assert jobs["bob"].proc is not None
        wait(lambda: jobs["bob"].state != "running", what="bob's enrolment went on")
        assert jobs["bob"].state == "cancelled" and "stopped asking" in jobs["bob"].detail
        wait(lambda: jobs["bob"].exitcode is not None, what="the enrolment process lives on")
        assert jobs["bob"].exitcode == -9
        wait(lambda: work_files(tmp_path) == [], what=str(work_files(tmp_path)))
        assert not (tmp_path / "ann").exists() and not (tmp_path / "bob").exists()
