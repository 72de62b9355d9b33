"""What every frame source is and gives: its errors, frames, description and assets.

The vocabulary shared by the sources (:mod:`articast.service.sources`) and the recordings
they replay (:mod:`articast.service.record`), kept apart so that neither imports the other
for it (they imported each other before).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from articast.core.errors import ArticastError
from articast.core.tracking.result import TrackResult


class SourceError(ArticastError):
    """A source that cannot work: bad URI, missing/corrupt file. Not retried."""


class SourceUnavailable(ArticastError):
    """A source that may come back (camera missing, busy or unplugged). Retried."""


@dataclass(frozen=True, eq=False)
class Frame:
    """One captured frame.

    index : source frame number (continues across loops).
    t : media time, s (container time stamp, or time since the camera opened).
    t_capture : ``time.monotonic()`` when the capture thread received the frame.
    image : (H, W, 3) uint8 BGR, or None for sources that carry only results (recordings).
    truth : ground truth for this frame, when the source knows it.
    """

    index: int
    t: float
    t_capture: float
    image: np.ndarray | None
    truth: TrackResult | None = None


@dataclass(frozen=True)
class SourceInfo:
    uri: str
    kind: str
    live: bool
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    frame_count: int | None = None
    detail: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"uri": self.uri, "kind": self.kind, "live": self.live, "width": self.width,
                "height": self.height, "fps": self.fps, "detail": dict(self.detail)}


@dataclass(frozen=True)
class SourceAssets:
    """What a source brings for tracking and for ``hello`` (synthetic speaker, recordings)."""

    model: Any = None  # articast.core.model.face.FaceModel
    camera: Any = None  # articast.core.model.camera.Camera
    appearance: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


class Source(Protocol):
    """What the capture thread drives. ``read`` returns ``(t, image, truth)`` or None at end."""

    uri: str
    live: bool
    pace: str  # "realtime" or "fast" (live sources: "realtime")
    loops: int  # 0 = forever

    def open(self) -> SourceInfo: ...

    def read(self) -> tuple[float, np.ndarray | None, TrackResult | None] | None: ...

    def close(self) -> None: ...

    def assets(self) -> SourceAssets: ...
