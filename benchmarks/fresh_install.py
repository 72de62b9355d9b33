"""The slow, full installation check (tests/test_packaging.py is the fast structural one).

In fresh virtual environments outside the repository, with the package index:
1. ``pip install REPO`` -> ``python -c "import core"`` fails, ``articast --help`` works;
2. ``pip install REPO/clients/python`` -> numpy and OpenCV are not installed, there is no
   ``articast`` command, ``import articast.client`` works.

``--demo`` also times the first-ever ``articast demo`` of that fresh install (issue 39: the
first frame within 60 s at load <= 2, no "stalled" or "crashed" line at any load): ``HOME`` is
an empty temporary folder (so is the speaker's asset cache, ``~/.cache/articast``: the user's
own is never read nor deleted) and numba's kernel cache is empty (``NUMBA_CACHE_DIR``; Python's
byte code is left as pip leaves it: compiled at install). Reported: seconds from the command to
each line it printed, to the URL and to the first frame a WebSocket subscriber gets, the CPU
seconds the demo and its worker had used by then (``cpu_s``: at load <= 2 on 2 cores the
wall-clock time is close to it), whether a line said "stalled" or "crashed", and the load
averages. ``--here`` runs that demo with this interpreter instead of installing (the same
empty caches; no download).

    python benchmarks/fresh_install.py --json      # a few minutes (downloads the dependencies)
    python benchmarks/fresh_install.py --here --demo --json   # the first demo only
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEMO_TIMEOUT_S = 600.0


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


async def _first_frame(url: str, timeout: float) -> None:
    import websockets

    async with websockets.connect(url, open_timeout=timeout, max_size=2**26) as ws:
        await ws.send(json.dumps({"type": "subscribe", "session": "demo"}))
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), timeout))
            if msg["type"] == "frame":
                return


def _tree_cpu(root: int) -> dict[int, float]:
    """CPU seconds (user + system) of ``root`` and its descendants, by pid (``/proc``)."""
    stats: dict[int, tuple[int, float]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    f = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(d)] = (int(f[1]), (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK"))
    tree, grew = {root}, True
    while grew:
        more = {pid for pid, (parent, _) in stats.items() if parent in tree} - tree
        tree |= more
        grew = bool(more)
    return {pid: stats[pid][1] for pid in tree if pid in stats}


def first_demo(python: Path | str, tmp: Path) -> dict[str, Any]:
    """The first ``articast demo`` run by ``python`` with every cache empty (under ``tmp``):
    seconds to each line it printed, to the URL (``--json``: one line) and to the first frame
    a subscriber receives; ``stalled`` / ``crashed``: whether a line said so."""
    home = tmp / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("ARTICAST_CACHE_DIR", "XDG_CACHE_HOME", "NUMBA_CACHE_DIR")}
    env.update(HOME=str(home), NUMBA_CACHE_DIR=str(tmp / "numba"))
    load = [round(x, 2) for x in os.getloadavg()]
    lines: list[tuple[float, str]] = []
    t0 = time.monotonic()
    proc = subprocess.Popen([str(python), "-m", "articast.service.cli", "demo", "--port", "0",
                             "--json"], cwd=tmp, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)

    def said() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append((round(time.monotonic() - t0, 1), line.rstrip()))

    reader = threading.Thread(target=said, daemon=True)
    reader.start()
    cpu: dict[int, float] = {}
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.wait(0.25):
            cpu.update(_tree_cpu(proc.pid))

    threading.Thread(target=sample, daemon=True).start()
    watchdog = threading.Timer(DEMO_TIMEOUT_S, proc.kill)  # a demo that hangs ends here
    watchdog.start()
    out: dict[str, Any] = {"load_before": load}
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if line:
            out["url_s"] = round(time.monotonic() - t0, 1)
            asyncio.run(_first_frame(json.loads(line)["url"], DEMO_TIMEOUT_S))
            out["first_frame_s"] = round(time.monotonic() - t0, 1)
            cpu.update(_tree_cpu(proc.pid))
            out["cpu_s"] = round(sum(cpu.values()), 1)
        else:
            out["error"] = "articast demo printed no URL"
    except (OSError, TimeoutError, ValueError) as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        sampling.set()
        watchdog.cancel()
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        reader.join(5)
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    out["lines"] = [f"{t:6.1f} s  {text}" for t, text in lines]
    out["stalled"] = any("stalled" in text for _, text in lines)
    out["crashed"] = any("crashed" in text for _, text in lines)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    ap.add_argument("--demo", action="store_true",
                    help="also time the first-ever 'articast demo' (every cache empty)")
    ap.add_argument("--here", action="store_true",
                    help="no install: the first demo with this interpreter (implies --demo)")
    args = ap.parse_args()
    if args.here:
        with tempfile.TemporaryDirectory(prefix="articast-first-demo-") as d:
            demo = first_demo(sys.executable, Path(d))
        ok = "first_frame_s" in demo and not demo["stalled"] and not demo["crashed"]
        out = {"demo": demo, "python": sys.executable, "cpus": os.cpu_count(), "ok": ok}
        print(json.dumps(out, indent=1) if args.json else out)
        sys.exit(0 if ok else 1)
    with tempfile.TemporaryDirectory(prefix="articast-install-") as d:
        tmp = Path(d)
        full = check(tmp, "full", ROOT)
        client = check(tmp, "client", ROOT / "clients" / "python")
        if args.demo and full.get("install_ok"):
            (tmp / "demo").mkdir()
            full["first_demo"] = first_demo(tmp / "full" / "bin" / "python", tmp / "demo")
    ok = (full.get("install_ok") and not full.get("import core")
          and full.get("articast --help ok") and client.get("install_ok")
          and not client.get("import numpy") and not client.get("articast script")
          and client.get("import articast.client"))
    demo: Any = full.get("first_demo")
    if demo is not None:
        ok = ok and "first_frame_s" in demo and not demo["stalled"] and not demo["crashed"]
    out = {"full": full, "client": client, "ok": bool(ok)}
    print(json.dumps(out, indent=1) if args.json else out)
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
