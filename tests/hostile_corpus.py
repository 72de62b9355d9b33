"""Issue 20, row k: a corpus of hostile files, generated, and a bounded runner for it.

:func:`build` writes the corpus into a folder: for every loader, files that are not files
(a FIFO, ``/dev/zero`` under the loader's file name), archives that declare more than they
hold (an ``.npy`` header of 1e14 elements, a 1.3 MB member that inflates to 1.25 GiB), JSON nested
100,000 deep, and values no real file has (1e308, 1e-300, NaN, time going back).

``python -m tests.hostile_corpus DIR`` (what the tests run, in a child process limited by
``RLIMIT_AS`` and per case by ``SIGALRM``) puts each file through its loader and prints one
JSON line per case: ``{"case", "outcome", "message"}`` where outcome is ``error`` (an
:class:`~articast.core.errors.ArticastError`: the CLI's one line and exit 2), ``loaded``,
``hang``, ``memory`` or ``exception`` (anything else: a traceback to a user).
"""

from __future__ import annotations

import io
import json
import os
import signal
import struct
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

DEEP = 100_000
CASE_SECONDS = 20
"""A case that takes longer hangs (the real ones never return); generous for a loaded machine."""


# ----------------------------------------------------------------------------- writers
def _npz_with(path: Path, valid: Path, replace: dict[str, bytes]) -> Path:
    """A copy of the valid archive ``valid`` with members replaced by raw bytes."""
    with zipfile.ZipFile(valid) as src, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            data = replace.get(info.filename, src.read(info))
            dst.writestr(info.filename, data)
    return path


def _npy_header(shape: tuple[int, ...], dtype: str = "<f8") -> bytes:
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode("latin-1")
    header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header


def _zip_bomb(path: Path, valid: Path, member: str, inflated: int) -> None:
    """``valid`` with ``member`` replaced by an ``.npy`` declaring ``inflated`` bytes of
    zeros, deflated (~1000:1): 1.25 GiB in a 1.3 MB file (the cap is 1 GiB; bigger bombs
    take longer to write, not to refuse)."""
    n = inflated // 8
    head = _npy_header((n,))
    with zipfile.ZipFile(valid) as src, zipfile.ZipFile(path, "w", compresslevel=1) as dst:
        for info in src.infolist():
            if info.filename != member:
                dst.writestr(info.filename, src.read(info), zipfile.ZIP_DEFLATED)
                continue
            zinfo = zipfile.ZipInfo(member)
            zinfo.compress_type = zipfile.ZIP_DEFLATED
            with dst.open(zinfo, "w", force_zip64=True) as out:
                out.write(head)
                chunk = bytes(1 << 20)
                left = n * 8
                while left > 0:
                    out.write(chunk[: min(left, len(chunk))])
                    left -= len(chunk)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _deep(n: int = DEEP) -> str:
    return "[" * n + "]" * n


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _zero(path: Path) -> Path:
    os.symlink("/dev/zero", path)
    return path


def _recording_lines(valid: Path) -> list[dict]:
    return [json.loads(x) for x in (valid / "rec.jsonl").read_text().splitlines()]


def _write_lines(path: Path, docs: list) -> Path:
    path.write_text("".join(json.dumps(d) + "\n" for d in docs))
    return path


# ----------------------------------------------------------------------------- the corpus
def build(out: Path, valid: Path) -> list[dict]:
    """Write the corpus into ``out`` (``valid`` holds one valid file per loader, see
    ``tests/test_hostile_files.py``). Returns the cases: ``{"case", "loader", "path"}``."""
    cases: list[dict] = []

    def case(name: str, loader: str, path: Path) -> None:
        cases.append({"case": name, "loader": loader, "path": str(path)})

    # not files: every loader, under its own file name
    for loader, name in (("model", "model.npz"), ("appearance", "appearance.npz"),
                         ("binding", "binding.npz"), ("corpus", "corpus.npz"),
                         ("camera", "camera.json"), ("recording", "rec.jsonl"),
                         ("fap", "talk.fap"), ("obj", "scan.obj"), ("track", "track.jsonl"),
                         ("token", "token"), ("video", "v.avi")):
        d = out / f"fifo-{loader}"
        d.mkdir()
        case(f"{loader}: a FIFO", loader, _fifo(d / name))
        d = out / f"zero-{loader}"
        d.mkdir()
        case(f"{loader}: /dev/zero", loader, _zero(d / name))
    d = out / "speaker-fifo"
    d.mkdir()
    for f in ("model.npz", "appearance.npz", "camera.json"):
        os.symlink(valid / f, d / f)
    _fifo(d / "speaker.json")
    case("speaker: speaker.json a FIFO", "speaker", d)

    # archives that declare more than they hold
    case("model: an .npy declaring 1e14 elements", "model",
         _npz_with(out / "huge-shape.npz", valid / "model.npz",
                   {"mean.npy": _npy_header((10**7, 10**7)) + bytes(64)}))
    _zip_bomb(out / "bomb.npz", valid / "model.npz", "mean.npy", 5 * 2**28)
    case("model: a 1.3 MB member inflating to 1.25 GiB, over the 1 GiB cap", "model",
         out / "bomb.npz")
    case("corpus: an .npy declaring 1e14 elements", "corpus",
         _npz_with(out / "huge-corpus.npz", valid / "corpus.npz",
                   {"postures.npy": _npy_header((10**7, 10**7, 3))}))

    # JSON nested 100,000 deep where a loader parses JSON
    doc = json.loads((valid / "camera.json").read_text())
    (out / "deep-camera.json").write_text(_deep())
    case("camera: nested 100,000 deep", "camera", out / "deep-camera.json")
    (out / "deep-k.json").write_text(json.dumps({**doc, "K": "X"}).replace('"X"', _deep()))
    case("camera: K nested 100,000 deep", "camera", out / "deep-k.json")
    d = out / "speaker-deep"
    d.mkdir()
    for f in ("model.npz", "appearance.npz", "camera.json"):
        os.symlink(valid / f, d / f)
    (d / "speaker.json").write_text(_deep())
    case("speaker: speaker.json nested 100,000 deep", "speaker", d)
    lines = _recording_lines(valid)
    rec_deep_header = out / "deep-header.jsonl"
    rec_deep_header.write_text(json.dumps({**lines[0], "geometry": "X"}).replace(
        '"X"', _deep()) + "\n" + "".join(json.dumps(x) + "\n" for x in lines[1:]))
    case("recording: header nested 100,000 deep", "recording", rec_deep_header)
    rec_deep_line = out / "deep-line.jsonl"
    rec_deep_line.write_text("".join(json.dumps(x) + "\n" for x in lines[:3]) + _deep() + "\n")
    case("recording: a frame line nested 100,000 deep", "recording", rec_deep_line)
    track_deep = out / "deep-track.jsonl"
    track_deep.write_text("".join(json.dumps(x) + "\n" for x in lines[1:3]) + _deep() + "\n")
    case("track: a line nested 100,000 deep", "track", track_deep)

    # values no real file has
    with np.load(valid / "model.npz") as z:
        mean, basis = z["mean"], z["basis"]
    for label, value in (("1e308", 1e308), ("-1e308", -1e308)):
        case(f"model: mean of {label}", "model",
             _npz_with(out / f"model-{label}.npz", valid / "model.npz",
                       {"mean.npy": _npy(np.full_like(mean, value))}))
    case("model: basis of 1e300", "model",
         _npz_with(out / "basis-1e300.npz", valid / "model.npz",
                   {"basis.npy": _npy(basis * 1e300)}))
    for label, changes in (("focal 1e-300", {"K": [[1e-300, 0, 32], [0, 1e-300, 24], [0, 0, 1]]}),
                           ("focal 1e308", {"K": [[1e+308, 0, 32], [0, 1e+308, 24], [0, 0, 1]]}),
                           ("centre 1e308", {"K": [[80, 0, 1e+308], [0, 80, 24], [0, 0, 1]]}),
                           ("dist 1e308", {"dist": [1e308, 0, 0, 0, 0]}),
                           ("focal 0.001 px", {"K": [[0.001, 0, 32], [0, 0.001, 24], [0, 0, 1]]})):
        p = out / f"camera-{label.replace(' ', '-')}.json"
        p.write_text(json.dumps({**doc, **changes}))
        case(f"camera: {label}", "camera", p)
    for label, coord in (("1e308", "1e308"), ("nan", "nan"), ("inf", "inf")):
        p = out / f"scan-{label}.obj"
        p.write_text(f"v 0 0 0\nv {coord} 0 0\nv 0 1 0\nf 1 2 3\n")
        case(f"obj: a coordinate of {label}", "obj", p)
    p = out / "scan-identical.obj"
    p.write_text("v 1 2 3\n" * 500 + "".join(f"f {i} {i + 1} {i + 2}\n" for i in range(1, 499)))
    case("obj: 500 identical vertices", "obj", p)
    for label, edit in (("t NaN", lambda x, i: {**x, "t": float("nan")} if i == 2 else x),
                        ("t going back", lambda x, i: {**x, "t": x["t"] - 10} if i == 3 else x),
                        ("t of 1e12", lambda x, i: {**x, "t": 1e12} if i == 2 else x),
                        ("alpha of 1e308", lambda x, i: {**x, "alpha": {
                            k: 1e308 for k in x["alpha"]}} if i == 2 else x),
                        ("translation of 1e308", lambda x, i: {**x, "pose": {
                            **x["pose"], "translation": [0, 0, 1e308]}} if i == 2 else x)):
        slug = label.replace(" ", "-")
        frames = [edit(x, i) for i, x in enumerate(lines[1:], 1)]
        case(f"recording: {label}", "recording",
             _write_lines(out / f"rec-{slug}.jsonl", [lines[0], *frames]))
        case(f"track: {label}", "track", _write_lines(out / f"track-{slug}.jsonl", frames))
    span = [dict(lines[1], t=0.0), dict(lines[2], t=1e9)]
    case("track: two frames 1e9 s apart", "track", _write_lines(out / "span.jsonl", span))
    big = out / "token-1g"
    with open(big, "wb") as fh:
        fh.truncate(2**30)  # sparse: costs no disk
    case("token: a 1 GB file", "token", big)
    return cases


# ----------------------------------------------------------------------------- loaders
def _loaders() -> dict:
    from articast.core.appearance.models import AppearanceModel
    from articast.core.dense.mesh import load_obj
    from articast.core.dense.transfer import Binding
    from articast.core.faces.speaker import Speaker
    from articast.core.model.build import Corpus
    from articast.core.model.camera import Camera
    from articast.core.model.face import FaceModel
    from articast.core.outputs.fap_io import read_fap
    from articast.service.commands.fap import read_track
    from articast.service.record import read_header
    from articast.service.security import load_token
    from articast.service.sources import make_source
    from articast.service.video import iter_video

    def recording(p):
        read_header(Path(p))
        src = make_source(f"replay-record:{p}?pace=fast")
        src.open()
        try:
            while src.read() is not None:
                pass
        finally:
            src.close()

    def appearance(p):
        from tests.service_helpers import small_model

        AppearanceModel.load(p, small_model())

    def video(p):
        for _ in iter_video(p):
            break

    def mesh(p):
        from articast.core.dense.mesh import check_scan

        check_scan(*load_obj(p), source=str(p))

    def track(p):
        from articast.core.model.face import PARAM_NAMES
        from articast.service.commands.fap import fap_frame_count

        results = read_track(Path(p), PARAM_NAMES)
        fap_frame_count(results, str(p))

    return {"model": FaceModel.load, "appearance": appearance, "binding": Binding.load,
            "corpus": Corpus.load, "camera": Camera.load, "recording": recording,
            "fap": read_fap, "obj": mesh, "track": track, "speaker": Speaker.load,
            "token": lambda p: load_token({}, str(p)), "video": video}


class _Hang(BaseException):
    pass


def _alarm(signum, frame):
    raise _Hang()


def run(cases: list[dict]) -> None:
    from articast.core.errors import ArticastError

    loaders = _loaders()
    signal.signal(signal.SIGALRM, _alarm)
    for c in cases:
        t0 = time.monotonic()
        outcome, message = "loaded", ""
        signal.alarm(CASE_SECONDS)
        try:
            loaders[c["loader"]](c["path"])
        except ArticastError as exc:
            outcome, message = "error", str(exc)
        except _Hang:
            outcome = "hang"
        except MemoryError:
            outcome = "memory"
        except BaseException as exc:  # noqa: BLE001 - what a user would see as a traceback
            outcome, message = "exception", f"{type(exc).__name__}: {str(exc)[:200]}"
        finally:
            signal.alarm(0)
        print(json.dumps({"case": c["case"], "outcome": outcome, "message": message[:500],
                          "seconds": round(time.monotonic() - t0, 2)}), flush=True)


if __name__ == "__main__":
    sys.setrecursionlimit(1000)  # Python's default, whatever the runner set
    run(json.loads(Path(sys.argv[1]).read_text()))
