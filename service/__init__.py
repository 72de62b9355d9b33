"""articast's service layer (everything that does I/O).

OpenCV and FFmpeg print their own diagnostics straight to stderr (a corrupt mp4 gave 5,001
lines): they are silenced here, before any video is opened, because every failure they could
report reaches the user as articast's own one-line error. Set the variables yourself to see
them again (e.g. ``OPENCV_FFMPEG_LOGLEVEL=32``).
"""

import os as _os

_os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
_os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
_os.environ.setdefault("OPENCV_VIDEOIO_DEBUG", "0")
