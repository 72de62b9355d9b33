"""Prometheus text exposition, written by hand (no dependency): counters, gauges, histograms."""

from __future__ import annotations

import bisect
import time
from collections import deque
from collections.abc import Iterable

LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0)
RESIDUAL_BUCKETS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class Histogram:
    __slots__ = ("buckets", "counts", "sum", "count")

    def __init__(self, buckets: Iterable[float] = LATENCY_BUCKETS) -> None:
        self.buckets = tuple(buckets)
        self.counts = [0] * (len(self.buckets) + 1)
        self.sum = 0.0
        self.count = 0

    def observe(self, v: float) -> None:
        self.counts[bisect.bisect_left(self.buckets, v)] += 1
        self.sum += v
        self.count += 1

    def lines(self, name: str, labels: str) -> list[str]:
        out, acc = [], 0
        for b, c in zip(self.buckets, self.counts, strict=False):
            acc += c
            out.append(f'{name}_bucket{{{labels},le="{b}"}} {acc}')
        out.append(f'{name}_bucket{{{labels},le="+Inf"}} {self.count}')
        out.append(f"{name}_sum{{{labels}}} {self.sum:.6f}")
        out.append(f"{name}_count{{{labels}}} {self.count}")
        return out


class RateMeter:
    """Events per second over the last ``window`` seconds."""

    def __init__(self, window: float = 2.0) -> None:
        self.window = window
        self._times: deque[float] = deque()

    def tick(self, t: float | None = None) -> None:
        t = time.monotonic() if t is None else t
        self._times.append(t)
        while self._times and self._times[0] < t - self.window:
            self._times.popleft()

    def rate(self) -> float:
        now = time.monotonic()
        while self._times and self._times[0] < now - self.window:
            self._times.popleft()
        return len(self._times) / self.window


class SessionMetrics:
    """Everything /metrics reports about one session."""

    def __init__(self) -> None:
        self.frames = 0
        self.frames_failed = 0
        self.failed_reasons: dict[str, int] = {}
        """Why frames were not ok (their quality's reason) -> how many."""
        self.source_dropped = 0
        self.subscriber_dropped = 0
        self.restarts = 0
        self.fps = RateMeter()
        self.track_latency = Histogram()  # capture -> tracked
        self.publish_latency = Histogram()  # tracked -> published on the hub
        self.send_latency = Histogram()  # tracked -> written to a subscriber's socket
        self.residual = Histogram(RESIDUAL_BUCKETS)
        self.last_residual = 0.0


HEADER = {
    "articast_frames_total": ("counter", "frames tracked"),
    "articast_frames_failed_total": ("counter", "frames tracked with ok=false"),
    "articast_fps": ("gauge", "frames tracked per second over the last 2 s"),
    "articast_source_dropped_total": ("counter", "frames the capture replaced before tracking"),
    "articast_subscriber_dropped_total": ("counter", "frames dropped for slow subscribers"),
    "articast_subscribers": ("gauge", "current subscribers"),
    "articast_restarts_total": ("counter", "worker restarts after a crash"),
    "articast_up": ("gauge", "1 if the session is running"),
    "articast_residual_last": ("gauge", "residual of the last frame"),
    "articast_residual": ("histogram", "tracking residual"),
    "articast_track_latency_seconds": ("histogram", "capture to tracked"),
    "articast_publish_latency_seconds": ("histogram", "tracked to published on the hub"),
    "articast_send_latency_seconds": ("histogram", "tracked to written to a subscriber socket"),
}


def render(sessions: dict[str, tuple[SessionMetrics, int, bool, int]], connections: int) -> str:
    """Prometheus text for ``{name: (metrics, subscribers, up, subscriber drops)}``."""
    rows: dict[str, list[str]] = {k: [] for k in HEADER}
    for name, (m, subs, up, sub_dropped) in sorted(sessions.items()):
        lab = f'session="{_escape(name)}"'
        rows["articast_frames_total"].append(f"articast_frames_total{{{lab}}} {m.frames}")
        rows["articast_frames_failed_total"].append(
            f"articast_frames_failed_total{{{lab}}} {m.frames_failed}")
        rows["articast_fps"].append(f"articast_fps{{{lab}}} {m.fps.rate():.3f}")
        rows["articast_source_dropped_total"].append(
            f"articast_source_dropped_total{{{lab}}} {m.source_dropped}")
        rows["articast_subscriber_dropped_total"].append(
            f"articast_subscriber_dropped_total{{{lab}}} {sub_dropped}")
        rows["articast_subscribers"].append(f"articast_subscribers{{{lab}}} {subs}")
        rows["articast_restarts_total"].append(f"articast_restarts_total{{{lab}}} {m.restarts}")
        rows["articast_up"].append(f"articast_up{{{lab}}} {int(up)}")
        rows["articast_residual_last"].append(
            f"articast_residual_last{{{lab}}} {m.last_residual:.6g}")
        rows["articast_residual"] += m.residual.lines("articast_residual", lab)
        for h in ("track", "publish", "send"):
            key = f"articast_{h}_latency_seconds"
            rows[key] += getattr(m, f"{h}_latency").lines(key, lab)
    out = []
    for key, (kind, doc) in HEADER.items():
        out += [f"# HELP {key} {doc}", f"# TYPE {key} {kind}", *rows[key]]
    out += ["# HELP articast_connections open WebSocket connections",
            "# TYPE articast_connections gauge", f"articast_connections {connections}"]
    return "\n".join(out) + "\n"


def _escape(v: str) -> str:
    return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
