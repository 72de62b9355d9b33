"""Real faces: face detection, landmarks and enrolment of a speaker from a video clip.

:class:`FaceFinder` (detector + 478-point landmarks on onnxruntime, MediaPipe's models
converted by ``tools/convert_face_models.py``) finds a :class:`Face` in a BGR frame and
tracks it from the previous frame's landmarks. ``models/canonical_face.npz`` holds
MediaPipe's metric canonical face (468 vertices in cm, triangles).
"""

from articast.core.faces.finder import Face, FaceFinder, FinderPolicy, models_dir

__all__ = ["Face", "FaceFinder", "FinderPolicy", "models_dir"]
