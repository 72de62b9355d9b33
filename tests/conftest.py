import numpy as np
import pytest

MEDIA_FILES = {"test_room.py", "test_room_redis.py", "test_webrtc.py"}
"""The test files that run real browsers, WebRTC media processes and room servers with their
trackers: they run one after another on one xdist worker (one ``xdist_group``), never beside
each other. Beside each other they starved each other's trackers on 2 cores (the two-browser
room test read a participant at 1-3 tracked frames a second and r 0.82-0.90 in three full
runs, 0.99 alone). Every other file is a group of its own, as ``--dist loadfile`` made it."""


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            name = item.path.name
            item.add_marker(pytest.mark.xdist_group("media" if name in MEDIA_FILES else name))


@pytest.fixture
def rng():
    return np.random.default_rng(1234)



@pytest.fixture(scope="session")
def speaker4_enrolled(tmp_path_factory):
    """Speaker 4 enrolled with the README's commands from a 20 s desk clip at 6 fps (sentence
    40): a folder holding ``clip/`` (the synthetic sequence) and ``speaker/`` (delegate
    included), made once for every test module that needs it. Modules work on their own copy
    (``copytree``), so this one stays as it was written."""
    from articast.service.cli import main

    d = tmp_path_factory.mktemp("speaker4")
    assert main(["synth", "sequence", "-o", str(d / "clip"), "--seed", "4", "--sentence", "40",
                 "--rig", "desk", "--frames", "120", "--fps", "6"]) == 0
    assert main(["enroll", str(d / "clip" / "video.mp4"), "-o", str(d / "speaker"),
                 "--quiet", "--json"]) == 0
    return d


@pytest.fixture(scope="module")
def media(tmp_path_factory):
    """A folder (per test module) holding a 2 s recording, talk.jsonl, for the service tests
    that serve one (``replay-record:``)."""
    from tests.service_helpers import write_recording

    root = tmp_path_factory.mktemp("media")
    write_recording(root / "talk.jsonl", frames=60, fps=30)
    return root
