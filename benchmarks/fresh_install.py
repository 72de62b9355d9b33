"""The slow, full installation check (tests/test_packaging.py is the fast structural one).

In fresh virtual environments outside the repository, with the package index:
1. ``pip install REPO`` -> ``python -c "import core"`` fails, ``articast --help`` works;
2. ``pip install REPO/clients/python`` -> numpy and OpenCV are not installed, there is no
   ``articast`` command, ``import articast.client`` works.

    python benchmarks/fresh_install.py --json      # a few minutes (downloads the dependencies)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def sh(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=1800)


def check(tmp: Path, name: str, target: Path) -> dict[str, object]:
    venv = tmp / name
    sh([sys.executable, "-m", "venv", str(venv)], tmp).check_returncode()
    py, t0 = venv / "bin" / "python", time.monotonic()
    r = sh([str(py), "-m", "pip", "install", "-q", str(target)], tmp)
    out: dict[str, object] = {"install_ok": r.returncode == 0,
                              "install_s": round(time.monotonic() - t0, 1)}
    if r.returncode:
        out["install_error"] = r.stderr[-2000:]
        return out
    for mod in ("core", "service", "clients", "numpy", "cv2", "articast.client",
                "articast.service"):
        out[f"import {mod}"] = sh([str(py), "-c", f"import {mod}"], tmp).returncode == 0
    script = venv / "bin" / "articast"
    out["articast script"] = script.exists()
    if script.exists():
        out["articast --help ok"] = sh([str(script), "--help"], tmp).returncode == 0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="articast-install-") as d:
        tmp = Path(d)
        full = check(tmp, "full", ROOT)
        client = check(tmp, "client", ROOT / "clients" / "python")
    ok = (full.get("install_ok") and not full.get("import core")
          and full.get("articast --help ok") and client.get("install_ok")
          and not client.get("import numpy") and not client.get("articast script")
          and client.get("import articast.client"))
    out = {"full": full, "client": client, "ok": bool(ok)}
    print(json.dumps(out, indent=1) if args.json else out)
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
