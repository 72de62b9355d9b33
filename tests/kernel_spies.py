"""Spies on the compiled kernels (core/tracking/kernels.py) for the tests that check that a
warm-up compiles every kernel, with every argument type, that tracking then calls."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class KernelSpies:
    """``wrap`` a kernel to record the numba types of each call's arguments, by name, in
    ``seen``; ``take`` hands over what was seen so far and starts afresh."""

    def __init__(self) -> None:
        self.seen: dict[str, set[tuple[Any, ...]]] = {}

    def wrap(self, name: str, kernel: Callable[..., Any]) -> Callable[..., Any]:
        from numba import typeof

        def spy(*args: Any) -> Any:
            self.seen.setdefault(name, set()).add(tuple(typeof(a) for a in args))
            return kernel(*args)
        return spy

    def take(self) -> dict[str, set[tuple[Any, ...]]]:
        out, self.seen = self.seen, {}
        return out
