"""The one-line warning when the tracked face does not look like the speaker folder's person
(issue 39, row 5): ``articast track --speaker`` and every serve or room session with a
speaker folder. It never refuses: a wrong folder tracks badly, but tracks."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from articast.core.faces.identity import WARN_DISTANCE, IdentityWatch


class IdentityWarning:
    """Watches a live tracker's first readings; says at most one line through ``say``.

    speaker : the :class:`~articast.core.faces.speaker.Speaker` tracked; where : how the user
    named its folder (the message quotes it). A folder enrolled before the check holds no
    signature: that is said once, at the start.
    """

    def __init__(self, speaker: Any, say: Callable[[str], None], where: str = "") -> None:
        self.say = say
        self.where = where or "the speaker folder"
        self.watch = IdentityWatch(dict(speaker.identity))
        self.warned = False
        if not speaker.identity and speaker.rig == "desk":
            say(f"{self.where} was enrolled before the identity check: the face is not "
                "checked against it (enrol again to have it checked)")

    def see(self, tracker: Any) -> None:
        """After each frame tracked by ``tracker`` (a LiveTracker)."""
        if self.watch.done:
            return
        reading = tracker.reading
        if reading is None:
            return
        d = self.watch.add(reading)
        if d is not None and d > WARN_DISTANCE:
            self.warned = True
            self.say(f"the face does not look like the person of {self.where} (distance "
                     f"{d:.1f}, usual < {WARN_DISTANCE:g}): wrong --speaker?")
