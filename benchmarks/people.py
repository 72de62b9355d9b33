"""Who is in which clip, and the two halves of the people that design choices are made on.

A design choice is made on one half of the *people* and checked on the other, then the halves
swap (issue 38): two clips of one person are never split between the halves. A clip whose
person is not listed here is its own person (its name), so a new clip dropped into the clips
folder is judged without a list to edit; it goes to the half that
:func:`half` draws for its name.

    python benchmarks/people.py [--clips DIR]      # the halves of the clips there
"""

from __future__ import annotations

import argparse
import random
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import CLIP_CACHE, clip_paths  # noqa: E402

#: clips of one person (../shared/clips/CLIPS.md: "same man as", "same woman as"; the
#: fetched cap12 and cap13 are one man at his webcam)
SAME_PERSON = {
    "styletalk_andrew_clip_1": "andrew", "styletalk_andrew_clip_2": "andrew",
    "styletalk_feifeili_clip1": "feifeili", "styletalk_feifeili_clip2_short": "feifeili",
    "cap12": "cap", "cap13": "cap",
}
SEED = 38  # the number: fixed before any result was seen
#: the people of the corpus when the halves were drawn (../shared/clips and the clips
#: tools/fetch_real_clips.py fetches), shuffled with SEED and dealt alternately: the halves
#: hold as many people each, whatever clips are present
KNOWN = ("edtalk_mouth_source", "edtalk_pose_source1", "edtalk_pose_source2",
         "facerealtime_driving", "latentsync_demo1_video", "latentsync_demo3_video",
         "lia_obama", "lia_vox_driving3", "liveportrait_d10", "metricaltracker_duda_video",
         "metricaltracker_wojtek_video", "minimates_driving", "andrew", "feifeili",
         "franck", "cap", "carphone", "single_face", "pexels_woman")
_order = sorted(KNOWN)
random.Random(SEED).shuffle(_order)
HALF = {p: "AB"[i % 2] for i, p in enumerate(_order)}


def person(clip: str) -> str:
    return SAME_PERSON.get(clip, clip)


def half(clip: str) -> str:
    """"A" or "B": the half of the people the clip's person is in (:data:`HALF`; a person
    not known then, by a coin drawn from the name and :data:`SEED` alone)."""
    p = person(clip)
    return HALF.get(p) or "AB"[random.Random(f"{SEED}:{p}").random() < 0.5]


def halves(clips: list[str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {"A": [], "B": []}
    for c in clips:
        out[half(c)].append(c)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=Path, default=CLIP_CACHE)
    args = ap.parse_args()
    for h, cs in halves(sorted(clip_paths(args.clips))).items():
        print(f"{h} ({len({person(c) for c in cs})} people): {' '.join(cs)}")


if __name__ == "__main__":
    main()
