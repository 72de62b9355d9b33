"""The built-in synthetic speaker: embedded default and test bed for every accuracy claim.

- :mod:`.geometry` - procedural face (points, groups, mesh, MPEG-4 labels) and its non-linear
  articulation by 7 ground-truth controls.
- :mod:`.corpus` - the 68-posture corpus (``make_corpus``).
- :mod:`.texture`, :mod:`.scene`, :mod:`.render` - textures, render parts and the z-buffered
  software renderer (``RenderOptions``).
- :mod:`.sequence` - talking sequences with head motion and ground truth (``make_sequence``).
- :mod:`.speaker` - ``SyntheticSpeaker`` / ``default_speaker`` tying them together.
"""

from articast.core.synthetic.corpus import make_corpus
from articast.core.synthetic.geometry import SpeakerGeometry, make_geometry
from articast.core.synthetic.render import RenderOptions
from articast.core.synthetic.sequence import (
    RIGS,
    Sequence,
    default_camera,
    make_sequence,
    rest_pose,
)
from articast.core.synthetic.speaker import SyntheticSpeaker, default_speaker
from articast.core.synthetic.stream import open_stream

__all__ = [
    "RIGS",
    "RenderOptions",
    "Sequence",
    "SpeakerGeometry",
    "SyntheticSpeaker",
    "default_camera",
    "default_speaker",
    "make_corpus",
    "make_geometry",
    "make_sequence",
    "open_stream",
    "rest_pose",
]
