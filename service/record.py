"""Recordings: one JSONL file per session run, written by the worker that tracks.

Line 1 is a header (``{"type": "header", "format": "articast-record", ...}``: the session's
model, camera and source, everything ``hello`` needs); every further line is one tracked frame
(a superset of ``TrackResult.to_dict``: ``seq``, ``frame``, ``t``, ``t_capture``,
``t_tracked``, ``alpha``, ``pose``, ``quality``). Each line is written whole and flushed, so a
crash loses at most the frame in flight; a reader ignores a truncated last line.

Plain ``articast track`` output (TrackResult lines without a header) replays too.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path
from typing import Any, TextIO

from articast.core.errors import ArticastError
from articast.core.model.face import PARAM_NAMES
from articast.core.tracking.result import TrackResult
from articast.service.jsonsafe import dumps
from articast.service.source_types import SourceAssets, SourceError
from articast.service.wire import FrameRecord, model_from_description

RECORD_FORMAT = "articast-record"
RECORD_VERSION = 1


class Recorder:
    """Appends a session run's frames to ``DIR/<session>-<UTC time>.jsonl``."""

    def __init__(self, directory: str | os.PathLike[str], session: str,
                 description: dict[str, Any], source: dict[str, Any]) -> None:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        self.path = d / f"{session}-{stamp}-{os.getpid()}.jsonl"
        n = 1
        while self.path.exists():
            n += 1
            self.path = d / f"{session}-{stamp}-{os.getpid()}-{n}.jsonl"
        self.param_names = list(description["param_names"])
        self._fh: TextIO | None = self.path.open("x", encoding="utf-8")
        self._line({"type": "header", "format": RECORD_FORMAT, "version": RECORD_VERSION,
                    "session": session, "started": time.time(), "source": source,
                    **description})

    def _line(self, doc: dict[str, Any]) -> None:
        assert self._fh is not None
        self._fh.write(dumps(doc, separators=(",", ":")) + "\n")
        self._fh.flush()

    def write(self, record: FrameRecord) -> None:
        if self._fh is not None:
            self._line(record.to_json(self.param_names))

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def read_header(path: Path) -> tuple[dict[str, Any], SourceAssets, tuple[str, ...]]:
    """The header of a recording (or defaults for headerless ``articast track`` output)."""
    from articast.core.errors import InputError
    from articast.core.safe_io import MAX_TEXT_BYTES, open_regular_text

    try:
        with open_regular_text(path, max_bytes=None) as fh:
            first = fh.readline(MAX_TEXT_BYTES)
    except InputError as exc:
        raise SourceError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: cannot read: {exc}") from None
    try:
        doc = json.loads(first)
    except RecursionError:
        raise SourceError(f"{path}: line 1: JSON nested too deeply") from None
    except ValueError:
        raise SourceError(f"{path}: not a JSONL recording (line 1 is not JSON)") from None
    if not isinstance(doc, dict):
        raise SourceError(f"{path}: not a JSONL recording")
    if doc.get("type") != "header":
        if "alpha" not in doc:
            raise SourceError(f"{path}: neither an articast recording nor track output")
        names = tuple(doc["alpha"]) if isinstance(doc["alpha"], dict) else PARAM_NAMES
        return {}, SourceAssets(), names
    if doc.get("format") != RECORD_FORMAT or doc.get("version") != RECORD_VERSION:
        raise SourceError(f"{path}: unsupported recording {str(doc.get('format'))[:40]!r} "
                          f"version {str(doc.get('version'))[:40]!r}")
    listed = doc.get("param_names")
    # a source of another type was an AttributeError at the replay's open
    if not isinstance(doc.get("source", {}), dict) or not isinstance(listed, list) or not all(
            isinstance(n, str) for n in listed):
        raise SourceError(f"{path}: malformed header: 'source' must be an object and "
                          "'param_names' a list of names")
    try:
        model = model_from_description(doc)
        camera = None
        if doc.get("camera"):
            from articast.core.model.camera import Camera

            camera = Camera.from_dict(doc["camera"], where=str(path))
    except (KeyError, TypeError, ValueError, RecursionError) as exc:
        raise SourceError(f"{path}: malformed header: {type(exc).__name__}: "
                          f"{str(exc)[:200]}") from None
    return doc, SourceAssets(model=model, camera=camera), tuple(doc["param_names"])


def parse_frame_line(line: str, param_names: tuple[str, ...]) -> TrackResult | None:
    """One recording line -> TrackResult (None for headers and blank lines)."""
    if not line.strip():
        return None
    try:
        doc = json.loads(line)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    if not isinstance(doc, dict):
        raise ValueError("not a JSON object")
    if doc.get("type") == "header":
        return None
    try:
        return TrackResult.from_dict(doc, param_names)
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"missing or malformed field {exc}") from None
    except ArticastError as exc:  # a pose of absurd values
        raise ValueError(str(exc)) from None


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)
