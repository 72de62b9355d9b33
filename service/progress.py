"""A small progress line for long offline work: redrawn in place on a terminal, a line every
10 % otherwise (so logs of CI or a pipe stay short), nothing when quiet."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    def __init__(self, total: int, label: str, stream: TextIO | None = None,
                 quiet: bool = False) -> None:
        self.total, self.label = max(int(total), 0), label
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.perf_counter()
        self.done = 0
        self._last_decile = -1

    def update(self, n: int = 1, note: str = "") -> None:
        self.done += n
        if self.quiet:
            return
        rate = self.done / max(time.perf_counter() - self.start, 1e-9)
        if self.total:
            frac = min(self.done / self.total, 1.0)
            bar = "#" * int(frac * 30)
            text = f"{self.label} [{bar:<30}] {self.done}/{self.total} {rate:6.1f}/s {note}"
        else:
            frac, text = 0.0, f"{self.label} {self.done} {rate:6.1f}/s {note}"
        if self.tty:
            self.stream.write("\r" + text[:120].ljust(80))
            self.stream.flush()
        elif self.total and int(frac * 10) > self._last_decile:
            self._last_decile = int(frac * 10)
            self.stream.write(text.rstrip() + "\n")

    def say(self, text: str) -> None:
        """A line of its own (a warning: said even when quiet), the bar redrawn below it on
        the next update."""
        if self.tty and not self.quiet:
            self.stream.write("\r" + " " * 80 + "\r")
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty and not self.quiet:
            self.stream.write("\n")
            self.stream.flush()
