import numpy as np
import pytest


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
