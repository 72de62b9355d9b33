"""The eyes' and brows' landmarks in MediaPipe's face topology (FaceMesh v1's 468 points; the
first 468 of FaceLandmarker v2's 478 are the same), read by the upper face
(:mod:`articast.core.faces.upper`) and its pixel measures (:mod:`~articast.core.faces.iris`,
:mod:`~articast.core.faces.lids`, :mod:`~articast.core.faces.brows`)."""

SIDES = ("left", "right")
"""The speaker's own left and right (ARKit's and VRM's convention)."""
EYE_CORNERS = {"left": (362, 263), "right": (133, 33)}
"""(inner, outer) corners of each eye."""
LID_PAIRS = {"left": ((386, 374), (385, 380), (387, 373)),
             "right": ((159, 145), (158, 153), (160, 144))}
"""(upper, lower) lid landmark pairs, middle first."""
EYE_CONTOUR = {
    "left": (362, 398, 384, 385, 386, 387, 388, 466, 263, 249, 390, 373, 374, 380, 381, 382),
    "right": (133, 173, 157, 158, 159, 160, 161, 246, 33, 7, 163, 144, 145, 153, 154, 155)}
"""Each eye's contour, in order round the eye."""
BROW_POINTS = {"left": {"inner": (336, 285), "outer": (300, 276)},
               "right": {"inner": (107, 55), "outer": (70, 46)}}
"""Brow landmarks (upper, lower edge) at the inner and outer ends."""
