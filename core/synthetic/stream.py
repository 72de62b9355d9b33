"""An endless talking stream of the synthetic speaker, for the service's ``synthetic:``
source: model, camera, a trained appearance model, and frames with their ground truth."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from articast.core.appearance.models import AppearanceModel
from articast.core.model.build import invert
from articast.core.model.camera import Camera, Pose
from articast.core.model.face import FaceModel
from articast.core.synthetic.enrol import enrolment_appearance
from articast.core.synthetic.render import RenderOptions
from articast.core.synthetic.sequence import default_camera, make_sequence, rest_pose
from articast.core.synthetic.speaker import default_speaker
from articast.core.tracking.result import TrackResult

CHUNK_S = 10.0  # each chunk is a fresh sequence of this length; time runs on across chunks


@dataclass
class SyntheticStream:
    seed: int
    fps: float
    rig: str
    model: FaceModel
    camera: Camera
    appearance: AppearanceModel
    initial_pose: Pose
    frame_count: int | None = None
    _chunk: int = field(default=0, repr=False)

    def frames(self) -> Iterator[tuple[float, np.ndarray, TrackResult]]:
        """Yield ``(t, image_bgr, truth)`` forever (truth alpha = direct inversion)."""
        speaker = default_speaker(self.seed)
        n = max(int(round(CHUNK_S * self.fps)), 2)
        index = 0
        while True:
            seq = make_sequence(self.seed * 1000 + 7 + self._chunk, n, self.fps, self.rig)
            alpha = invert(self.model, seq.points)
            for i in range(seq.n_frames):
                t = index / self.fps
                img = speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                                     RenderOptions(seed=(index * 7919) % 1_000_003))
                yield t, img, TrackResult(index, t, alpha[i], seq.pose(i))
                index += 1
            self._chunk += 1


def open_stream(seed: int = 0, fps: float = 30.0, rig: str = "head",
                kind: str = "la_quad") -> SyntheticStream:
    """The stream of speaker ``seed``; trains its appearance model first (a few seconds)."""
    speaker = default_speaker(seed)
    return SyntheticStream(seed, float(fps), rig, speaker.model(), default_camera(rig),
                           enrolment_appearance(speaker, rig, kind), rest_pose(rig))
