"""An endless talking stream of the synthetic speaker, for the service's ``synthetic:``
source: model, camera, a trained appearance model, and frames with their ground truth.

Building the speaker's model (~0.4 s) and training its appearance on 75 rendered enrolment
frames (~8 s) is what made ``articast demo`` slow to start. Both are deterministic functions of
the seed, the rig, the appearance kind and this package's code, so :func:`open_stream` keeps
them in ``cache_dir`` (the service passes ``$ARTICAST_CACHE_DIR`` or ``~/.cache/articast``):
one folder per key, whose name carries a digest of the source of every module that shapes them
(:func:`asset_key`). A changed module is a new key: stale assets are never loaded, and the
first start after the change trains again (once). The speaker's texture atlas (~0.4 s to
build at the first rendered frame) is kept there too.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from articast.core.appearance.models import AppearanceModel
from articast.core.errors import ArticastError, InputError
from articast.core.model.build import invert
from articast.core.model.camera import Camera, Pose
from articast.core.model.face import FaceModel
from articast.core.synthetic.enrol import enrolment_appearance
from articast.core.synthetic.render import RenderOptions
from articast.core.synthetic.sequence import default_camera, make_sequence, rest_pose
from articast.core.synthetic.speaker import default_speaker
from articast.core.synthetic.texture import make_atlas, preset_atlas
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

    def frames(self, start: int = 0) -> Iterator[tuple[float, np.ndarray, TrackResult]]:
        """Yield ``(t, image_bgr, truth)`` forever (truth alpha = direct inversion), from
        frame ``start`` on (the frames before it are not rendered: the same frames as
        skipping them, without their cost)."""
        speaker = default_speaker(self.seed)
        n = max(int(round(CHUNK_S * self.fps)), 2)
        index = 0
        while True:
            seq = make_sequence(self.seed * 1000 + 7 + self._chunk, n, self.fps, self.rig)
            if index + seq.n_frames <= start:  # (a whole chunk before the start)
                index += seq.n_frames
                self._chunk += 1
                continue
            alpha = invert(self.model, seq.points)
            for i in range(seq.n_frames):
                if index < start:
                    index += 1
                    continue
                t = index / self.fps
                img = speaker.render(seq.controls[i], seq.pose(i), seq.camera,
                                     RenderOptions(seed=(index * 7919) % 1_000_003))
                yield t, img, TrackResult(index, t, alpha[i], seq.pose(i))
                index += 1
            self._chunk += 1


_CORE = Path(__file__).resolve().parent.parent
_SHAPING = ("synthetic", "model", "appearance")
"""Sub-packages of ``articast.core`` whose code determines the cached model and appearance."""


def asset_key(seed: int, rig: str, kind: str) -> str:
    """Name of the cache folder of speaker ``seed``'s model and ``kind`` appearance on ``rig``:
    the inputs plus a digest of the source of every module in :data:`_SHAPING`."""
    digest = hashlib.sha256()
    for sub in _SHAPING:
        for path in sorted((_CORE / sub).glob("*.py")):
            digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return f"synthetic-{int(seed)}-{rig}-{kind}-{digest.hexdigest()[:16]}"


def speaker_assets(seed: int, rig: str = "head", kind: str = "la_quad",
                   cache_dir: str | os.PathLike[str] | None = None,
                   progress: Callable[[str], None] | None = None
                   ) -> tuple[FaceModel, AppearanceModel]:
    """Speaker ``seed``'s model and trained appearance, from ``cache_dir`` when it has them
    (else built, trained and saved there; ``None``: no cache). A cache that cannot be written
    (read-only, full disk) only costs the next start the same training again. ``progress``
    is told, in one line, when the assets have to be built."""
    folder = Path(cache_dir) / asset_key(seed, rig, kind) if cache_dir is not None else None
    if folder is not None and (folder / "appearance.npz").is_file():
        try:
            model = FaceModel.load(folder / "model.npz")
            appearance = AppearanceModel.load(folder / "appearance.npz", model)
            _load_atlas(seed, folder / "atlas.npy")
            return model, appearance
        except ArticastError:
            pass  # a damaged cache entry: rebuild it below
    if progress is not None:
        progress(f"building synthetic speaker {seed}'s model, {kind} appearance and texture "
                 + (f"(first run only, a few seconds; cached in {folder.parent})"
                    if folder is not None else "(no cache: ARTICAST_CACHE_DIR=off)"))
    speaker = default_speaker(seed)
    model = speaker.model()
    appearance = enrolment_appearance(speaker, rig, kind)
    if folder is not None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            model.save(folder / "model.npz")
            tmp = folder / "atlas.tmp.npy"
            np.save(tmp, make_atlas(seed).image)
            os.replace(tmp, folder / "atlas.npy")
            appearance.save(folder / "appearance.npz")  # written last: marks a whole entry
        except OSError:
            pass
    return model, appearance


def _load_atlas(seed: int, path: Path) -> None:
    """Use the cached texture atlas (rendering's first frame would build it, ~0.4 s); an
    entry without one (or a damaged one) only costs that time."""
    import io

    from articast.core.safe_io import read_regular_bytes

    try:  # a regular file of bounded size: a FIFO put in the cache would block np.load
        atlas = np.load(io.BytesIO(read_regular_bytes(path, 256 * 2**20)), allow_pickle=False)
        preset_atlas(seed, atlas)
    except (OSError, ValueError, EOFError, InputError):
        pass


def open_stream(seed: int = 0, fps: float = 30.0, rig: str = "head", kind: str = "la_quad",
                cache_dir: str | os.PathLike[str] | None = None,
                progress: Callable[[str], None] | None = None) -> SyntheticStream:
    """The stream of speaker ``seed``: its model and trained appearance come from
    ``cache_dir`` when there (:func:`speaker_assets`), else are built first (~5 s)."""
    model, appearance = speaker_assets(seed, rig, kind, cache_dir, progress)
    return SyntheticStream(seed, float(fps), rig, model, default_camera(rig), appearance,
                           rest_pose(rig))
