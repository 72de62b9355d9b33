"""The one exception hierarchy of articast.

::

    ArticastError                 base of everything we raise on purpose
    ├── ModelFileError            a model/appearance/corpus/camera file is wrong or corrupt
    ├── InputError                bad input at a boundary (shapes, NaN, unknown names)
    └── CalibrationError          calibration could not be computed from the given images

A frame that cannot be tracked is *not* an exception: it is a result with ``ok=False``
and a reason (see :mod:`articast.core.tracking.tracker`).
"""


class ArticastError(Exception):
    """Base class of every error articast raises on purpose."""


class ModelFileError(ArticastError):
    """A file could not be loaded: wrong kind or version, wrong shapes, NaN, truncated."""


class InputError(ArticastError, ValueError):
    """An argument is malformed: wrong shape, non-finite values, unknown names."""


class CalibrationError(ArticastError):
    """Camera calibration failed (too few usable images, pattern not found)."""
