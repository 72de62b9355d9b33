"""Shared by the benchmarks: a server in a subprocess (its own GIL and core), inputs, stats."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


ONE_ADDRESS = ("--max-connections-per-client", "5000", "--max-subscriptions-per-client", "5000",
               "--max-subscribes-per-client-s", "100000", "--max-handshakes-per-client-s",
               "100000", "--reserved-subscribers", "0")
"""Server options for a load generator on loopback: its hundreds of subscribers come from one
address, which the per-address limits (issue 20, row e/f: 256 connections, 256
subscriptions, 20 subscribes/s; issue 39: 20 connections/s, the last 200 subscriptions kept
for other addresses) rightly refuse; without these the clients never connect."""


VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".y4m", ".mpg", ".mpeg")
"""What a clips folder's videos end with (any case)."""


SHARED_CLIPS = ROOT.parent / "shared/clips"
#: the clips folder by default: the team's shared one beside the repository where it is there
#: (read as it is: every video in it), else the one ``tools/fetch_real_clips.py`` fills
CLIP_CACHE = SHARED_CLIPS if SHARED_CLIPS.is_dir() else Path.home() / ".cache/articast/clips"


def clip_paths(folder: Path) -> dict[str, Path]:
    """Every clip of a folder, by name, in name order: the entries of its ``clips.json`` where
    there is one (``tools/fetch_real_clips.py`` writes it), else every video file in it, named
    by its stem (``../shared/clips`` as it is: no list to write by hand). Empty when the
    folder does not exist."""
    meta = folder / "clips.json"
    if meta.is_file():
        return {r["name"]: Path(r["path"]) for r in json.loads(meta.read_text())}
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir())
            if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES}


def load_average() -> list[float]:
    """The machine's 1-, 5- and 15-minute load averages (``uptime``), rounded: every timing
    figure states the load it was taken at (the development machine's 2 cores are shared)."""
    return [round(x, 2) for x in os.getloadavg()]


def make_recording(frames: int, fps: float, n_points: int = 200) -> Path:
    """A ground-truth recording that the truth processor replays at ``fps``."""
    from tests.service_helpers import small_model, write_recording

    path = Path(tempfile.mkdtemp(prefix="articast-bench-")) / f"bench-{fps:g}.jsonl"
    write_recording(path, frames=frames, fps=fps, model=small_model(n=n_points))
    return path


class Server:
    """``articast serve`` in a subprocess on 127.0.0.1, any free port."""

    def __init__(self, sources: dict[str, str], *extra: str) -> None:
        args = [sys.executable, "-m", "articast.service.cli", "serve", "--port", "0", "--json",
                "--log-level", "error"]
        for name, uri in sources.items():
            args += ["--source", f"{name}={uri}"]
        self.proc = subprocess.Popen([*args, *extra], cwd=ROOT, stdout=subprocess.PIPE,
                                     text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if not line:
            raise RuntimeError("the server did not start")
        self.url = json.loads(line)["url"]
        self.http = self.url.replace("ws://", "http://").rsplit("/", 1)[0]
        self.pid = self.proc.pid

    def rss_mb(self) -> float:
        with open(f"/proc/{self.pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        return float("nan")

    def cpu_s(self) -> float:
        with open(f"/proc/{self.pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

    def wait_running(self, timeout: float = 20.0) -> None:
        import httpx

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                states = httpx.get(self.http + "/healthz", timeout=2).json()["sessions"]
                if states and all(s == "running" for s in states.values()):
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError("sessions did not start")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    i = min(len(v) - 1, max(0, round(q / 100 * (len(v) - 1))))
    return v[i]
