"""``SyntheticSpeaker``: the built-in speaker in one object (geometry, corpus, model, images).

    speaker = default_speaker(seed=0)
    corpus = speaker.corpus()                  # 68 postures with their generating controls
    model = speaker.model()                    # build_model(corpus) (cached)
    points = speaker.points(controls)          # true geometry (..., N, 3), never the model's
    image = speaker.render(controls, pose, camera, RenderOptions(noise_sigma=2))
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from articast.core.errors import InputError
from articast.core.model.build import Corpus, VarianceTable, build_model
from articast.core.model.camera import Camera, Pose
from articast.core.model.face import PARAM_NAMES, FaceModel
from articast.core.synthetic.corpus import make_corpus
from articast.core.synthetic.geometry import SpeakerGeometry, make_geometry
from articast.core.synthetic.render import RenderOptions, composite, visible_points
from articast.core.synthetic.scene import build_scene
from articast.core.synthetic.texture import Atlas, make_atlas, make_background


@dataclass(eq=False)
class SyntheticSpeaker:
    """The synthetic speaker of one seed. Caches its corpus, model and textures."""

    seed: int = 0
    noise_mm: float = 0.3
    geometry: SpeakerGeometry = field(init=False)
    _cache: dict = field(init=False, default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.geometry = make_geometry(self.seed)

    @property
    def n_points(self) -> int:
        return self.geometry.n_points

    def corpus(self) -> Corpus:
        """The 68-posture corpus (with ``noise_mm`` measurement noise)."""
        if "corpus" not in self._cache:
            self._cache["corpus"] = make_corpus(self.seed, self.noise_mm, self.geometry)
        return self._cache["corpus"]

    def model_and_table(self) -> tuple[FaceModel, VarianceTable]:
        """``build_model(self.corpus())`` (cached)."""
        if "model" not in self._cache:
            self._cache["model"] = build_model(self.corpus())
        return self._cache["model"]

    def model(self) -> FaceModel:
        """The linear model built from the corpus (for trackers; never used for rendering)."""
        return self.model_and_table()[0]

    def points(self, controls: np.ndarray) -> np.ndarray:
        """True geometry: controls (..., 7) -> (..., N, 3) mm head frame."""
        return self.geometry.articulate(controls)

    def rest_controls(self) -> np.ndarray:
        return np.zeros(len(PARAM_NAMES))

    def render(self, controls: np.ndarray, pose: Pose, camera: Camera,
               options: RenderOptions | None = None, upper: dict | None = None) -> np.ndarray:
        """One frame of the true articulated face: controls (7,) -> (H, W, 3) uint8 BGR.

        upper : the eyes and brows (:mod:`articast.core.synthetic.upper`, a dict as
        ``UpperTruth.frame`` gives); None: the static painted ones (open, looking ahead)."""
        c = np.asarray(controls, np.float64)
        if c.shape != (len(PARAM_NAMES),):
            raise InputError(f"render takes one posture, controls of shape (7,), got {c.shape}")
        if not isinstance(pose, Pose) or not isinstance(camera, Camera):
            raise InputError("render needs a Pose and a Camera (articast.core.model.camera)")
        options = options or RenderOptions()
        atlas = make_atlas(self.seed)
        scene = self._scene(c)
        bg = make_background(camera.width, camera.height, self.seed) if options.background else None
        image = atlas.image
        if upper is not None:
            from articast.core.synthetic.upper import paint_upper

            image = paint_upper(self.seed, (upper["closure_left"], upper["closure_right"]),
                                (upper["gaze_yaw_deg"], upper["gaze_pitch_deg"]),
                                (upper["raise_left_mm"], upper["raise_right_mm"]))
        return composite(scene, pose, camera, options, image, bg)


    def visible(self, controls: np.ndarray, pose: Pose, camera: Camera) -> np.ndarray:
        """(N,) bool: which model points the camera sees at ``controls`` and ``pose``
        (inside the image and not hidden by the lips, the nose, the cheeks...)."""
        c = np.asarray(controls, np.float64)
        if c.shape != (len(PARAM_NAMES),):
            raise InputError(f"visible takes one posture, controls of shape (7,), got {c.shape}")
        return visible_points(self._scene(c), self.points(c), pose, camera)

    def _scene(self, c: np.ndarray):
        skin_uv = self._cache.get("skin_uv")
        if skin_uv is None:
            skin_uv = self._cache["skin_uv"] = Atlas.skin_uv(self.geometry.uv)
        return build_scene(self.geometry, self.points(c), c, skin_uv)


def default_speaker(seed: int = 0) -> SyntheticSpeaker:
    """The built-in speaker of ``seed`` (cached per seed, so its model is built once)."""
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    if int(seed) not in _SPEAKERS:
        _SPEAKERS[int(seed)] = SyntheticSpeaker(int(seed))
    return _SPEAKERS[int(seed)]


_SPEAKERS: dict[int, SyntheticSpeaker] = {}
