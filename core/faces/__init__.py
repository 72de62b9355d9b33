"""Real faces: face detection, landmarks and enrolment of a speaker from a video clip.

:class:`FaceFinder` (detector + 478-point landmarks on onnxruntime, MediaPipe's models
converted by ``tools/convert_face_models.py``) finds a :class:`Face` in a BGR frame and
tracks it from the previous frame's landmarks. :func:`canonical_face` loads MediaPipe's
metric canonical face (468 vertices in mm, triangles, landmark groups, lip contours).
"""

from articast.core.faces.canonical import CanonicalFace, canonical_face
from articast.core.faces.finder import Face, FaceFinder, FinderPolicy, models_dir

__all__ = ["CanonicalFace", "Face", "FaceFinder", "FinderPolicy", "canonical_face", "models_dir"]
