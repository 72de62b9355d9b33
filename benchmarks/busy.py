"""A stand-in for a CPU-heavy tracker: pure-Python work holding the GIL, then the truth.

``--processor benchmarks.busy:Busy`` (ARTICAST_BUSY_MS sets the work per frame, default 8 ms).
"""

from __future__ import annotations

import os
import time
from typing import Any


class Busy:
    def __init__(self, context: Any) -> None:
        self.seconds = float(os.environ.get("ARTICAST_BUSY_MS", "8")) / 1000.0

    def process(self, frame: Any) -> Any:
        end = time.perf_counter() + self.seconds
        x = 0
        while time.perf_counter() < end:
            x += 1  # the GIL is held, as in a Python-level optimiser loop
        return frame.truth
