"""JSON that is JSON: no ``NaN`` or ``Infinity`` in anything articast writes.

Python's ``json`` writes ``NaN`` by default, which no strict reader accepts. Every writer in
the service goes through :func:`dumps`: a non-finite ``residual`` becomes ``-1`` (unknown, as
on the wire), any other non-finite number becomes ``null``, and ``allow_nan=False`` makes
a forgotten case an error instead of a corrupt file.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

UNKNOWN = {"residual": -1.0}
"""Keys whose unknown value has a documented number instead of null."""


def finite(obj: Any, key: str = "") -> Any:
    """``obj`` with every non-finite float replaced (numpy scalars and arrays become lists)."""
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else UNKNOWN.get(key)
    if isinstance(obj, dict):
        return {k: finite(v, str(k)) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v, key) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist(), key)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def dumps(obj: Any, **kw: Any) -> str:
    return json.dumps(finite(obj), allow_nan=False, **kw)
