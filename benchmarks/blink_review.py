"""dlib's blink events as confirmed by looking at the frames (``blink_review.json``, read by
``blinks.py`` and ``corpus_summary.py``): no landmark model is the truth, and an
eye-aspect-ratio dip is also a look down."""

from __future__ import annotations

import json
from pathlib import Path

REVIEW = Path(__file__).resolve().parent / "blink_review.json"


def confirmed(name: str, ours: list[tuple[int, int]], ref: list[tuple[int, int]],
              review: dict | None = None
              ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """articast's events and dlib's as confirmed by looking (``REVIEW``, module docstring):
    the reference without the events a ``not_blinks`` or ``unsure`` range overlaps, with
    the ``blinks`` ranges added; articast's events without those an ``unsure`` range
    overlaps."""
    if review is None:
        review = json.loads(REVIEW.read_text()) if REVIEW.is_file() else {}
    clip = review.get("clips", {}).get(name, {})

    def hit(e: tuple[int, int], key: str) -> bool:
        return any(e[0] < b and a < e[1] for a, b, *_ in clip.get(key, []))

    ref_c = [e for e in ref if not hit(e, "not_blinks") and not hit(e, "unsure")]
    ref_c = sorted(ref_c + [(int(a), int(b)) for a, b, *_ in clip.get("blinks", [])])
    return [e for e in ours if not hit(e, "unsure")], ref_c
