"""Issue 20, row k: a corpus of hostile files, generated, and a bounded runner for it.

:func:`build` writes the matrix into a folder: every loader the product has (:data:`FILES`:
model, appearance, corpus, dense binding, landmark observation model, delegate, camera,
speaker folder, .obj scan, scan landmarks, recording, track, truth lines, .fap, token file,
a video for track/enroll and for a ``file:`` source, an ``images:`` folder) given each of
the :data:`GENERIC` kinds in place of its file (a FIFO, ``/dev/zero``, an empty file, the
valid file truncated, binary garbage, UTF-16 text, a folder, a dangling and a looping
symlink), and then what applies to each loader: archives that declare more than they hold
(an ``.npy`` header of 1e14 elements, a 1.3 MB member that inflates to 1.25 GiB, a pickle),
JSON nested 100,000 deep, JSON of the wrong types, values no real file has (NaN, inf, 1e308,
1e-300, negative where a size is), degenerate geometry (every point at one place, on one
line), time stamps NaN / going back / 1e12 / 1e9 s apart, a PNG declaring 1e10 pixels.
Each valid file is a case too (it must load). A case is an error unless marked
``expect: loaded`` (the few correct files: see :data:`CORRECT` and the labels).

``python -m tests.hostile_corpus CASES.json`` (what the tests run, in a child process
limited by ``RLIMIT_AS`` and per case by ``SIGALRM``) puts each file through its loader and
prints one JSON line per case: ``{"case", "loader", "kind", "expect", "outcome", "message",
"seconds"}`` where outcome is ``error`` (an :class:`~articast.core.errors.ArticastError`:
the CLI's one line and exit 2), ``loaded``, ``hang``, ``memory`` or ``exception`` (anything
else: a traceback to a user). Before each case it writes a marker line to stderr, so
anything a library prints there is attributed to its case.
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
MARK = "@@ case: "
"""Written to stderr before each case: anything a loader writes there (a library's own
message) is then attributed to its case, and counted as a second line to a user."""
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
FILES = {  # loader: (its file's name, text or not)
    "model": ("model.npz", False), "appearance": ("appearance.npz", False),
    "corpus": ("corpus.npz", False), "binding": ("binding.npz", False),
    "points": ("points_v1.npz", False), "delegate": ("delegate.npz", False),
    "camera": ("camera.json", True), "speaker": ("speaker.json", True),
    "obj": ("scan.obj", True), "landmarks": ("lm.json", True), "recording": ("rec.jsonl", True),
    "track": ("track.jsonl", True), "jsonl": ("truth.jsonl", True), "fap": ("talk.fap", True),
    "token": ("token", True), "video": ("v.avi", False), "file-source": ("v.avi", False),
    "images": ("x.png", False),
}
"""Every loader the product has and the file it reads. ``speaker`` is a speaker folder (the
hostile file is its speaker.json), ``images`` an ``images:`` source folder (the hostile file is
its one image), ``track`` what ``export-fap`` reads, ``jsonl`` the truth/track lines ``track
--train`` and the evaluations read, ``file-source`` a video given to ``serve``/``track-worker``
as ``file:`` (what ``track`` and ``enroll`` read is ``video``)."""

GENERIC = ("a FIFO", "/dev/zero", "an empty file", "truncated to half", "binary garbage",
           "not UTF-8 (UTF-16)", "a folder", "a dangling symlink", "a symlink loop")
"""What every loader is given in place of its file (``not UTF-8`` for text loaders only)."""

CORRECT = {
    ("camera", "not UTF-8 (UTF-16)"): "JSON's own encodings: read to the same values",
    ("speaker", "not UTF-8 (UTF-16)"): "JSON's own encodings: read to the same values",
    ("token", "truncated to half"): "a shorter token is a token (serve refuses < 16 bytes)",
}
"""Generic cases whose file is a correct one: loaded, rightly."""

NPZ = ("model", "appearance", "corpus", "binding", "points", "delegate")


def _valid_source(loader: str, valid: Path) -> Path:
    """The valid file a loader's hostile variants are made from."""
    name = FILES[loader][0]
    if loader == "speaker":
        return valid / "speaker" / name
    if loader == "images":
        return valid / "images" / name
    if loader == "track":
        return valid / "truth.jsonl"
    return valid / name


def _generic(path: Path, kind: str, data: bytes, seed: int) -> Path:
    """``path`` made into ``kind`` (one of :data:`GENERIC`) from the valid bytes ``data``."""
    if kind == "a FIFO":
        return _fifo(path)
    if kind == "/dev/zero":
        return _zero(path)
    if kind == "an empty file":
        path.write_bytes(b"")
    elif kind == "truncated to half":
        path.write_bytes(data[: len(data) // 2])
    elif kind == "binary garbage":
        path.write_bytes(np.random.default_rng(seed).bytes(4096))
    elif kind == "not UTF-8 (UTF-16)":
        path.write_bytes(data.decode("utf-8").encode("utf-16"))
    elif kind == "a folder":
        path.mkdir()
    elif kind == "a dangling symlink":
        os.symlink(path.parent / "nothing-here", path)
    elif kind == "a symlink loop":
        os.symlink(path.with_name(path.name + ".loop"), path)
        os.symlink(path, path.with_name(path.name + ".loop"))
    return path


def _folder_with(out: Path, slug: str, valid_dir: Path, name: str) -> Path:
    """A copy (by links) of the folder ``valid_dir`` without ``name``: the case puts its
    hostile file there."""
    d = out / slug
    d.mkdir()
    for f in valid_dir.iterdir():
        if f.name != name:
            os.symlink(f, d / f.name)
    return d / name


def _bundle_with(path: Path, valid: Path, kind: str, arrays: dict | None = None,
                 meta: dict | None = None, drop_meta: tuple[str, ...] = ()) -> Path:
    """A bundle like ``valid`` (an articast ``.npz`` of ``kind``) with arrays or metadata
    replaced: written by the product's own writer, so only the replaced values are wrong."""
    from articast.core.bundle import _META_KEY, save_bundle

    with np.load(valid) as z:
        old = {k: z[k] for k in z.files if k != _META_KEY}
        doc = json.loads(bytes(z[_META_KEY]).decode("utf-8"))
    doc.update(meta or {})
    for k in drop_meta:
        doc.pop(k, None)
    version = doc.pop("version")
    doc.pop("kind")
    if isinstance(version, int):
        save_bundle(path, kind, version, {**old, **(arrays or {})}, doc)
    return path


def build(out: Path, valid: Path) -> list[dict]:
    """Write the corpus into ``out`` (``valid`` holds one valid file per loader, see
    ``tests/test_hostile_files.py``). Returns the cases: ``{"case", "loader", "kind",
    "path"}`` and ``"expect": "loaded"`` for the few that are correct files."""
    cases: list[dict] = []

    def case(loader: str, kind: str, path: Path, expect: str = "error") -> None:
        c = {"case": f"{loader}: {kind}", "loader": loader, "kind": kind, "path": str(path)}
        if expect != "error":
            c["expect"] = expect
        cases.append(c)

    # every loader x every generic kind, under the loader's own file name
    for i, (loader, (name, text)) in enumerate(FILES.items()):
        src = _valid_source(loader, valid)
        case(loader, "the valid file", src.parent if loader in ("speaker", "images") else src,
             expect="loaded")
        data = src.read_bytes()
        for j, kind in enumerate(GENERIC):
            if kind.startswith("not UTF-8") and not text:
                continue
            slug = f"{loader}-{j}"
            expect = "loaded" if (loader, kind) in CORRECT else "error"
            if loader in ("speaker", "images"):
                path = _folder_with(out, slug, src.parent, name)
                _generic(path, kind, data, 1000 * i + j)
                case(loader, kind, path.parent, expect)
            else:
                (out / slug).mkdir()
                case(loader, kind, _generic(out / slug / name, kind, data, 1000 * i + j), expect)

    # folders that are not folders, and a speaker's other files that are not files
    for j, kind in enumerate(("a FIFO", "an empty file", "a dangling symlink", "a symlink loop")):
        for loader in ("speaker", "images"):
            d = out / f"{loader}-dir-{j}"
            d.mkdir()
            case(loader, f"the folder is {kind}", _generic(d / "folder", kind, b"", j))
    for member in ("model.npz", "appearance.npz", "camera.json", "points_v1.npz"):
        for j, kind in enumerate(("a FIFO", "a dangling symlink", "a folder")):
            slug = f"speaker-{member.split('.')[0]}-{j}"
            path = _folder_with(out, slug, valid / "speaker", member)
            _generic(path, kind, b"", j)
            case("speaker", f"its {member} is {kind}", path.parent)

    # archives that declare more than they hold, under every archive loader
    _zip_bomb(out / "bomb.npz", valid / "model.npz", "mean.npy", 5 * 2**28)
    for loader in NPZ:
        d = out / f"npz-{loader}"
        d.mkdir()
        name = FILES[loader][0]
        os.link(out / "bomb.npz", d / f"bomb-{name}")
        case(loader, "a 1.3 MB member inflating to 1.25 GiB, over the 1 GiB cap",
             d / f"bomb-{name}")
        with zipfile.ZipFile(valid / name) as z:
            member = next(n for n in z.namelist() if n != "__meta__.npy")
        case(loader, "an .npy declaring 1e14 elements",
             _npz_with(d / f"huge-{name}", valid / name,
                       {member: _npy_header((10**7, 10**7)) + bytes(64)}))
        case(loader, "metadata of the wrong JSON type (a list)",
             _npz_with(d / f"meta-list-{name}", valid / name,
                       {"__meta__.npy": _npy(np.frombuffer(b"[1, 2]", np.uint8))}))
        case(loader, "metadata nested 100,000 deep",
             _npz_with(d / f"meta-deep-{name}", valid / name,
                       {"__meta__.npy": _npy(np.frombuffer(_deep().encode(), np.uint8))}))
        case(loader, "an object (pickle) array",
             _npz_with(d / f"pickle-{name}", valid / name,
                       {member: _npy_header((1,), "|O") + b"\x80\x04N."}))
        for label, value in (("NaN", np.nan), ("inf", np.inf), ("1e308", 1e308)):
            with np.load(valid / name) as z:
                arr = z[member.removesuffix(".npy")]
            if arr.dtype.kind == "f":
                case(loader, f"{member.removesuffix('.npy')} of {label}",
                     _npz_with(d / f"{label}-{name}", valid / name,
                               {member: _npy(np.full_like(arr, value))}))

    # values no real file has, loader by loader
    from articast.core.appearance.models import APPEARANCE_KIND
    from articast.core.delegate.build import DELEGATE_KIND
    from articast.core.dense.transfer import BINDING_KIND
    from articast.core.model.face import MODEL_KIND
    from articast.core.tracking.points import POINT_MODEL_KIND

    bundle = {"model": MODEL_KIND, "points": POINT_MODEL_KIND, "delegate": DELEGATE_KIND,
              "appearance": APPEARANCE_KIND, "binding": BINDING_KIND}
    with np.load(valid / "model.npz") as z:
        mean, basis = z["mean"], z["basis"]
    for label, value in (("-1e308", -1e308),):
        case("model", f"mean of {label}",
             _npz_with(out / f"model-{label}.npz", valid / "model.npz",
                       {"mean.npy": _npy(np.full_like(mean, value))}))
    case("model", "basis of 1e300",
         _npz_with(out / "basis-1e300.npz", valid / "model.npz",
                   {"basis.npy": _npy(basis * 1e300)}))
    case("model", "every point at the same place (degenerate geometry)",
         _bundle_with(out / "model-same.npz", valid / "model.npz", bundle["model"],
                      {"mean": np.zeros_like(mean) + 5.0}))
    case("model", "a basis of 1e-300 (no parameter moves anything)",
         _bundle_with(out / "model-tiny.npz", valid / "model.npz", bundle["model"],
                      {"basis": np.full_like(basis, 1e-300)}))
    case("model", "triangles indexing past the points",
         _bundle_with(out / "model-tri.npz", valid / "model.npz", bundle["model"],
                      {"triangles": np.array([[0, 1, 10**6]], np.int32)}))
    case("model", "version of the wrong type (a string)",
         _npz_with(out / "model-version.npz", valid / "model.npz", {"__meta__.npy": _npy(
             np.frombuffer(json.dumps({"kind": "face-model", "version": "1"}).encode(),
                           np.uint8))}))
    with np.load(valid / "points_v1.npz") as z:
        sigma = z["sigma_mm"]
    for label, value in (("0", 0.0), ("-1", -1.0), ("1e-300", 1e-300)):
        case("points", f"sigma_mm of {label}",
             _bundle_with(out / f"points-sigma{label}.npz", valid / "points_v1.npz",
                          bundle["points"], {"sigma_mm": np.full_like(sigma, value)}))
    case("points", "network of the wrong type (a list)",
         _bundle_with(out / "points-net.npz", valid / "points_v1.npz", bundle["points"],
                      meta={"network": [1, 2]}))
    case("points", "offset_p99 of the wrong type (a string): unknown, as documented",
         _bundle_with(out / "points-p99.npz", valid / "points_v1.npz", bundle["points"],
                      meta={"offset_p99": "x"}), expect="loaded")
    case("points", "landmark indices negative",
         _bundle_with(out / "points-neg.npz", valid / "points_v1.npz", bundle["points"],
                      {"landmarks": -np.arange(1, 1 + len(sigma))}))
    with np.load(valid / "delegate.npz") as z:
        dv = z["vertices"]
    case("delegate", "every vertex at the same place (degenerate geometry)",
         _bundle_with(out / "delegate-same.npz", valid / "delegate.npz", bundle["delegate"],
                      {"vertices": np.zeros_like(dv)}))
    case("delegate", "param_names of the wrong type (a number)",
         _bundle_with(out / "delegate-names.npz", valid / "delegate.npz", bundle["delegate"],
                      meta={"param_names": 7}))
    case("delegate", "uv of 1e15",
         _bundle_with(out / "delegate-uv.npz", valid / "delegate.npz", bundle["delegate"],
                      {"uv": np.full((len(dv), 2), 1e15)}))
    case("appearance", "sigma of the wrong type (a string)",
         _bundle_with(out / "appearance-sigma.npz", valid / "appearance.npz",
                      bundle["appearance"], meta={"sigma": "x"}))
    case("binding", "lambda2 negative",
         _bundle_with(out / "binding-lambda.npz", valid / "binding.npz", bundle["binding"],
                      meta={"lambda2": -1.0}))
    case("corpus", "an .npy declaring 1e14 elements (3-D)",
         _npz_with(out / "huge-corpus.npz", valid / "corpus.npz",
                   {"postures.npy": _npy_header((10**7, 10**7, 3))}))

    # JSON nested 100,000 deep where a loader parses JSON
    doc = json.loads((valid / "camera.json").read_text())
    (out / "deep-camera.json").write_text(_deep())
    case("camera", "nested 100,000 deep", out / "deep-camera.json")
    (out / "deep-k.json").write_text(json.dumps({**doc, "K": "X"}).replace('"X"', _deep()))
    case("camera", "K nested 100,000 deep", out / "deep-k.json")
    path = _folder_with(out, "speaker-deep", valid / "speaker", "speaker.json")
    path.write_text(_deep())
    case("speaker", "speaker.json nested 100,000 deep", path.parent)
    lines = _recording_lines(valid)
    rec_deep_header = out / "deep-header.jsonl"
    rec_deep_header.write_text(json.dumps({**lines[0], "geometry": "X"}).replace(
        '"X"', _deep()) + "\n" + "".join(json.dumps(x) + "\n" for x in lines[1:]))
    case("recording", "header nested 100,000 deep", rec_deep_header)
    rec_deep_line = out / "deep-line.jsonl"
    rec_deep_line.write_text("".join(json.dumps(x) + "\n" for x in lines[:3]) + _deep() + "\n")
    case("recording", "a frame line nested 100,000 deep", rec_deep_line)
    for loader in ("track", "jsonl"):
        p = out / f"deep-{loader}.jsonl"
        p.write_text("".join(json.dumps(x) + "\n" for x in lines[1:3]) + _deep() + "\n")
        case(loader, "a line nested 100,000 deep", p)
    (out / "deep-lm.json").write_text(_deep())
    case("landmarks", "nested 100,000 deep", out / "deep-lm.json")

    # the camera: numbers and types no calibration has
    for label, changes in (
            ("focal 1e-300", {"K": [[1e-300, 0, 32], [0, 1e-300, 24], [0, 0, 1]]}),
            ("focal 1e308", {"K": [[1e+308, 0, 32], [0, 1e+308, 24], [0, 0, 1]]}),
            ("focal negative", {"K": [[-80, 0, 32], [0, -80, 24], [0, 0, 1]]}),
            ("focal NaN", {"K": [[float("nan"), 0, 32], [0, 80, 24], [0, 0, 1]]}),
            ("focal inf", {"K": [[float("inf"), 0, 32], [0, 80, 24], [0, 0, 1]]}),
            ("centre 1e308", {"K": [[80, 0, 1e+308], [0, 80, 24], [0, 0, 1]]}),
            ("dist 1e308", {"dist": [1e308, 0, 0, 0, 0]}),
            ("focal 0.001 px", {"K": [[0.001, 0, 32], [0, 0.001, 24], [0, 0, 1]]}),
            ("width negative", {"width": -64}), ("width 0", {"width": 0}),
            ("size 1e12 px", {"width": 10**12, "height": 10**12}),
            ("width 1e308", {"width": 1e308}),
            ("K of the wrong type (a string)", {"K": "80 0 32"}),
            ("K of the wrong shape (2x2)", {"K": [[80, 0], [0, 80]]}),
            ("K of strings", {"K": [["a", "b", "c"]] * 3}),
            ("K of the wrong type (an object)", {"K": {"fx": 80}}),
            ("dist of the wrong type (a string)", {"dist": "0 0 0 0 0"}),
            ("dist of 100,000 numbers", {"dist": [0.0] * 100_000}),
            ("width of the wrong type (a list)", {"width": [64]}),
            ("width as a string of digits (\"64\": read as 64)", {"width": "64"})):
        p = out / f"camera-{len(cases)}.json"
        p.write_text(json.dumps({**doc, **changes}))
        case("camera", label, p, "loaded" if label.endswith("read as 64)") else "error")
    p = out / "camera-list.json"
    p.write_text("[1, 2, 3]")
    case("camera", "a JSON list, not an object", p)

    # speaker.json: types and values no enrolment writes
    sdoc = json.loads((valid / "speaker" / "speaker.json").read_text())
    for label, changes in (
            ("rig of the wrong type (a list)", {"rig": ["desk"]}),
            ("residual of the wrong type (a string)", {"residual": "x"}),
            ("residual NaN", {"residual": {**sdoc["residual"], "median": float("nan")}}),
            ("residual negative", {"residual": {**sdoc["residual"], "p95": -1}}),
            ("residual 1e308", {"residual": {**sdoc["residual"], "p99": 1e308}}),
            ("residual frames 1e308", {"residual": {**sdoc["residual"], "frames": 1e308}}),
            ("motion of the wrong type (a string)", {"motion": "x"}),
            ("motion q negative", {"motion": {"q": [-1.0] * 13, "v0": [1.0] * 13}}),
            ("motion q of 1e308", {"motion": {"q": [1e308] * 13, "v0": [1.0] * 13}}),
            ("upper of the wrong type (a number)", {"upper": 5}),
            ("upper of the wrong type (a list)", {"upper": [1, 2]}),
            ("identity of the wrong type (a number)", {"identity": 5}),
            ("identity signature NaN", {"identity": [{"network": "v1", "frames": 40,
                                                      "median": [float("nan")] * 240,
                                                      "spread": [0.01] * 240}]}),
            ("identity spread 0", {"identity": [{"network": "v1", "frames": 40,
                                                 "median": [0.1] * 240,
                                                 "spread": [0.0] * 240}]}),
            ("version of the wrong type (a string)", {"version": "1"}),
            ("a JSON list, not an object", None)):
        path = _folder_with(out, f"speaker-v{len(cases)}", valid / "speaker", "speaker.json")
        path.write_text(json.dumps([1, 2]) if changes is None else json.dumps({**sdoc, **changes}))
        case("speaker", f"speaker.json {label}", path.parent)

    # .obj scans: numbers and geometry no scan has
    for label, coord in (("1e308", "1e308"), ("nan", "nan"), ("inf", "inf"), ("-1e308", "-1e308")):
        p = out / f"scan-{label}.obj"
        p.write_text(f"v 0 0 0\nv {coord} 0 0\nv 0 1 0\nf 1 2 3\n")
        case("obj", f"a coordinate of {label}", p)
    p = out / "scan-identical.obj"
    p.write_text("v 1 2 3\n" * 500 + "".join(f"f {i} {i + 1} {i + 2}\n" for i in range(1, 499)))
    case("obj", "500 identical vertices", p)
    for label, text_ in (
            ("500 vertices on a line", "".join(f"v {i} {2 * i} 0\n" for i in range(500))
             + "".join(f"f {i} {i + 1} {i + 2}\n" for i in range(1, 499))),
            ("every coordinate 1e-300", "v 0 0 0\nv 1e-300 0 0\nv 0 1e-300 0\nf 1 2 3\n"),
            ("a face indexing past the vertices", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n"),
            ("a face of index 0", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n"),
            ("a face of index 1e18", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 1000000000000000000\n"),
            ("a face indexing back past the start", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -9\n"),
            ("vertices with two coordinates", "v 0 0\nv 1 0\nv 0 1\nf 1 2 3\n"),
            ("coordinates not numbers", "v a b c\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")):
        p = out / f"scan-{len(cases)}.obj"
        p.write_text(text_)
        case("obj", label, p)

    p = out / "scan-points.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    # a point cloud was bound (1 M vertices, exit 0, a 90-101 mm error: issue 39): refused
    case("obj", "no faces (a point cloud, not a surface)", p)

    # landmarks: numbers and shapes no annotation has
    pts = json.loads((valid / "lm.json").read_text())
    for label, value in (
            ("a coordinate of 1e308", [[1e308, 0, 0], *pts[1:]]),
            ("every point NaN", [[float("nan")] * 3] * 68),
            ("every point at the same place", [[1.0, 2.0, 3.0]] * 68),
            ("67 points", pts[:67]), ("points of the wrong type (an object)", {"points": {"a": 1}}),
            ("coordinates of strings", [["a", "b", "c"]] * 68)):
        p = out / f"lm-{len(cases)}.json"
        p.write_text(json.dumps(value))
        case("landmarks", label, p)

    # recordings and tracks: time and values no tracker writes
    edits = (
        ("t NaN", lambda x, i: {**x, "t": float("nan")} if i == 2 else x),
        ("t going back", lambda x, i: {**x, "t": x["t"] - 10} if i == 3 else x),
        ("t of 1e12", lambda x, i: {**x, "t": 1e12} if i == 2 else x),
        ("t of the wrong type (a word)", lambda x, i: {**x, "t": "soon"} if i == 2 else x),
        ("alpha of 1e308", lambda x, i: {**x, "alpha": {
            k: 1e308 for k in x["alpha"]}} if i == 2 else x),
        ("alpha NaN", lambda x, i: {**x, "alpha": {
            k: float("nan") for k in x["alpha"]}} if i == 2 else x),
        ("alpha of the wrong type (a list)", lambda x, i: {**x, "alpha": [1, 2]} if i == 2 else x),
        ("translation of 1e308", lambda x, i: {**x, "pose": {
            **x["pose"], "translation": [0, 0, 1e308]}} if i == 2 else x),
        ("rotation NaN", lambda x, i: {**x, "pose": {
            **x["pose"], "rotation": [float("nan")] * 3}} if i == 2 else x),
        ("rotation of 2 numbers", lambda x, i: {**x, "pose": {
            **x["pose"], "rotation": [0, 0]}} if i == 2 else x),
        ("pose of the wrong type (a number)", lambda x, i: {**x, "pose": 5} if i == 2 else x),
        ("frame of 1e308", lambda x, i: {**x, "frame": 1e308} if i == 2 else x),
        ("quality of the wrong type (a string)",
         lambda x, i: {**x, "quality": "ok"} if i == 2 else x),
        ("a line that is a list", lambda x, i: [1, 2] if i == 2 else x),
        ("eyes and brows of 1e308: read as not seen, as documented", lambda x, i: {
            **x, "eyes": {"ok": True, "closure_left": 1e308, "gaze_yaw_deg": float("nan")},
            "brows": {"ok": True, "raise_inner_left_mm": -1e308}} if i == 2 else x))
    for label, edit in edits:
        slug = f"{len(cases)}"
        frames = [edit(x, i) for i, x in enumerate(lines[1:], 1)]
        expect = "loaded" if label.endswith("as documented") else "error"
        case("recording", label, _write_lines(out / f"rec-{slug}.jsonl", [lines[0], *frames]),
             expect)
        case("track", label, _write_lines(out / f"track-{slug}.jsonl", frames), expect)
    span = [dict(lines[1], t=0.0), dict(lines[2], t=1e9)]
    case("track", "two frames 1e9 s apart", _write_lines(out / "span.jsonl", span))
    for label, header in (
            ("header's param_names of the wrong type (a string)", {"param_names": "jaw1"}),
            ("header's geometry of the wrong type (a list)", {"geometry": [1, 2]}),
            ("header's source of the wrong type (a number)", {"source": 5}),
            ("header's format unknown", {"format": "something-else"})):
        case("recording", label, _write_lines(out / f"rec-h{len(cases)}.jsonl",
                                              [{**lines[0], **header}, *lines[1:]]))
    case("recording", "no header (track output, which replays)",
         _write_lines(out / "rec-noheader.jsonl", lines[1:]), expect="loaded")
    case("recording", "a header and no frame (an empty recording: nothing to replay)",
         _write_lines(out / "rec-header-only.jsonl", lines[:1]), expect="loaded")

    # .fap files: numbers no player takes
    fap = (valid / "talk.fap").read_text().split("\n")
    head = fap[0].split(" ")
    for label, new_head in (("fps 1e-12", [*head[:2], "0.000000000001", head[3]]),
                            ("fps 1e308", [*head[:2], "1" + "0" * 308, head[3]]),
                            ("frame count 1e18", [*head[:3], "1" + "0" * 18]),
                            ("fps of the wrong type (a word)", [*head[:2], "fast", head[3]])):
        p = out / f"fap-{len(cases)}.fap"
        p.write_text("\n".join([" ".join(new_head), *fap[1:]]))
        case("fap", label, p)
    values = fap[2].split(" ")
    for label, v in (("a value of 1e30", "1" + "0" * 30), ("a value of -9223372036854775809",
                                                         "-9223372036854775809")):
        p = out / f"fap-{len(cases)}.fap"
        p.write_text("\n".join([fap[0], fap[1], " ".join([values[0], v, *values[2:]]), *fap[3:]]))
        case("fap", label, p)

    # token files
    big = out / "token-1g"
    with open(big, "wb") as fh:
        fh.truncate(2**30)  # sparse: costs no disk
    case("token", "a 1 GB file", big)
    for label, data in (("only white space", b"  \n\t\n"), ("5,000 bytes", b"x" * 5000)):
        p = out / f"token-{len(cases)}"
        p.write_bytes(data)
        case("token", label, p)

    # videos: a container with no frame; a picture under a video's name (a one-frame clip,
    # which OpenCV reads as such: correct)
    import cv2

    w = cv2.VideoWriter(str(out / "no-frame.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 48))
    w.release()
    (out / "picture.avi").write_bytes((valid / "images" / "x.png").read_bytes())
    for loader in ("video", "file-source"):
        case(loader, "a container with no frame", out / "no-frame.avi")
        case(loader, "a PNG picture named .avi (a one-frame clip)", out / "picture.avi",
             expect="loaded")

    # images: a picture that declares more than it holds
    d = out / "images-huge"
    d.mkdir()
    (d / "x.png").write_bytes(_png_declaring(100_000, 100_000))
    case("images", "a PNG declaring 100,000 x 100,000 pixels", d)
    return cases


def _png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width`` x ``height`` RGB pixels, holding a few bytes."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(bytes(1000))) + chunk(b"IEND", b""))


# ----------------------------------------------------------------------------- loaders
def _loaders() -> dict:
    import articast.service  # noqa: F401 - first, as in the CLI: it quiets OpenCV's own logs
    from articast.core.appearance.models import AppearanceModel
    from articast.core.delegate.build import Delegate
    from articast.core.dense.landmarks import load_landmarks
    from articast.core.dense.mesh import load_obj
    from articast.core.dense.transfer import Binding
    from articast.core.faces.speaker import Speaker
    from articast.core.model.build import Corpus
    from articast.core.model.camera import Camera
    from articast.core.model.face import PARAM_NAMES, FaceModel
    from articast.core.outputs.fap_io import read_fap
    from articast.core.tracking.points import PointModel
    from articast.service.commands.fap import read_track
    from articast.service.commands.track import load_states
    from articast.service.record import read_header
    from articast.service.security import load_token
    from articast.service.sources import make_source
    from articast.service.video import iter_video

    def drain(uri: str) -> None:
        src = make_source(uri)
        src.open()
        try:
            while src.read() is not None:
                pass
        finally:
            src.close()

    def recording(p):
        read_header(Path(p))
        drain(f"replay-record:{p}?pace=fast")

    def appearance(p):
        from tests.service_helpers import small_model

        AppearanceModel.load(p, small_model())

    def video(p):
        for _ in iter_video(p):
            pass

    def mesh(p):
        from articast.core.dense.mesh import check_scan

        check_scan(*load_obj(p), source=str(p))

    def track(p):
        from articast.service.commands.fap import fap_frame_count

        results = read_track(Path(p), PARAM_NAMES)
        fap_frame_count(results, str(p))

    return {"model": FaceModel.load, "appearance": appearance, "binding": Binding.load,
            "corpus": Corpus.load, "points": lambda p: PointModel.load(p, len(PARAM_NAMES)),
            "delegate": Delegate.load, "camera": Camera.load, "recording": recording,
            "fap": read_fap, "obj": mesh, "landmarks": load_landmarks, "track": track,
            "jsonl": lambda p: load_states(Path(p), PARAM_NAMES), "speaker": Speaker.load,
            "token": lambda p: load_token({}, str(p)), "video": video,
            "file-source": lambda p: drain(f"file:{p}?pace=fast"),
            "images": lambda p: drain(f"images:{p}?pace=fast")}


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
        print(f"{MARK}{c['case']}", file=sys.stderr, flush=True)  # what follows is its own
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
        print(json.dumps({"case": c["case"], "loader": c["loader"], "kind": c["kind"],
                          "expect": c.get("expect", "error"), "outcome": outcome, "message": message[:500],
                          "seconds": round(time.monotonic() - t0, 2)}), flush=True)


if __name__ == "__main__":
    sys.setrecursionlimit(1000)  # Python's default, whatever the runner set
    run(json.loads(Path(sys.argv[1]).read_text()))
