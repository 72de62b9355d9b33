"""The installed distributions, in fresh virtual environments outside the repository.

* ``articast`` (the repository): its import names are its own (``articast.*``): ``import core``,
  ``import service``, ``import clients`` fail, ``articast --help`` works.
* ``articast-client`` (``clients/python``): installs with only its declared dependencies
  (websockets, pydantic): numpy and the server are not even importable there, it has no
  ``articast`` command, and its example command prints live frames from a real server.

Kept affordable for CI (~15 s): the wheels are built without build isolation and installed
with ``--no-deps``; the fresh environments see the third-party packages they need through a
folder of links into this environment (the main one: all of them; the client: only the
dependency closure of websockets and pydantic), never this checkout or its installation.
``benchmarks/fresh_install.py`` does the slow full check: ``pip install`` from the index.
"""

import importlib.metadata as md
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP = {".git", "__pycache__", "build", "dist", ".pytest_cache", ".hypothesis", ".venv", "out"}


def run(args, **kw):
    return subprocess.run(args, capture_output=True, text=True, timeout=300, **kw)


def dependency_closure(names):
    """Distributions needed by ``names`` (their non-extra requirements, recursively)."""
    seen, todo = set(), list(names)
    while todo:
        name = re.split(r"[ <>=!~;\[]", todo.pop(), maxsplit=1)[0].lower().replace("_", "-")
        if name in seen:
            continue
        seen.add(name)
        for req in md.requires(name) or []:
            if "extra ==" not in req:
                todo.append(req)
    return seen


def link_packages(dest, include):
    """Links in ``dest`` to the top-level entries of the installed distributions for which
    ``include(dist_name)`` is true; never articast's own."""
    dest.mkdir()
    for dist in md.distributions():
        name = dist.metadata["Name"].lower().replace("_", "-")
        if name.startswith("articast") or not include(name):
            continue
        for f in dist.files or []:
            top = f.parts[0]
            if top.endswith((".dist-info", ".pth")) or top in ("..", "__pycache__"):
                continue
            src = Path(dist.locate_file(top))
            if src.exists() and not (dest / top).exists():
                (dest / top).symlink_to(src)


def fresh_venv(path, deps_dir):
    run([sys.executable, "-m", "venv", "--without-pip", str(path)]).check_returncode()
    py = path / "bin" / "python"
    purelib = run([str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"])
    Path(purelib.stdout.strip(), "deps.pth").write_text(f"{deps_dir}\n")
    return py


def pip_install(py, wheel):
    r = run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
             "--no-index", str(wheel)])
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def wheels(tmp_path_factory):
    pytest.importorskip("wheel", reason="building a wheel offline needs the 'wheel' package "
                        "(in the test extra)")
    tmp = tmp_path_factory.mktemp("pkg")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=lambda d, names: [
        n for n in names if n in SKIP or n.endswith(".egg-info")])
    out = tmp / "wheels"
    r = run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
             "-w", str(out), str(src), str(src / "clients" / "python")], cwd=tmp)
    assert r.returncode == 0, r.stderr
    found = {w.name.split("-")[0]: w for w in out.glob("*.whl")}
    assert set(found) == {"articast", "articast_client"}, found
    return tmp, found


def test_full_distribution_has_only_its_own_import_names(wheels):
    tmp, found = wheels
    deps = tmp / "deps-all"
    link_packages(deps, lambda name: True)
    py = fresh_venv(tmp / "venv-full", deps)
    pip_install(py, found["articast"])
    outside = tmp / "elsewhere"
    outside.mkdir()
    for name in ("core", "service", "clients"):
        r = run([str(py), "-c", f"import {name}"], cwd=outside)
        assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, (name, r.stderr)
    r = run([str(py), "-c", "import articast.core.model, articast.service.cli, articast.client;"
             "print(articast.core.model.__file__)"], cwd=outside)
    assert r.returncode == 0, r.stderr
    assert str(tmp / "venv-full") in r.stdout and str(ROOT) not in r.stdout
    r = run([str(tmp / "venv-full" / "bin" / "articast"), "--help"], cwd=outside)
    assert r.returncode == 0, r.stderr
    assert "demo" in r.stdout and "serve" in r.stdout and "Traceback" not in r.stderr
    # the client's commands, which the docs and the client's help name, come with it too
    for name in ("articast-print", "articast-record"):
        exe = tmp / "venv-full" / "bin" / name
        assert exe.exists(), f"{name} is not installed by the articast distribution"
        r = run([str(exe), "--help"], cwd=outside)
        assert r.returncode == 0 and "token" in r.stdout and "Traceback" not in r.stderr, r


def test_client_distribution_alone(wheels, tmp_path):
    tmp, found = wheels
    need = dependency_closure(["websockets", "pydantic"])
    assert "numpy" not in need
    deps = tmp_path / "deps-client"
    link_packages(deps, lambda name: name in need)
    venv = tmp_path / "venv-client"
    py = fresh_venv(venv, deps)
    pip_install(py, found["articast_client"])
    requires = md.Distribution.at(next((venv / "lib").glob(
        "python*/site-packages/articast_client-*.dist-info"))).requires
    assert sorted(r.split(">")[0] for r in requires) == ["pydantic", "websockets"]
    assert not (venv / "bin" / "articast").exists()  # no server command to crash
    for name in ("numpy", "cv2", "fastapi", "articast.service", "articast.core"):
        r = run([str(py), "-c", f"import {name}"], cwd=tmp_path)
        assert r.returncode != 0, name
    # the client's example against a real server
    from tests.service_helpers import write_recording

    rec = tmp_path / "rec.jsonl"
    write_recording(rec, frames=300, fps=30.0)
    server = subprocess.Popen(
        [sys.executable, "-m", "articast.service.cli", "replay-record", str(rec), "--name",
         "rec", "--port", "0", "--json", "--loop"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        url = json.loads(server.stdout.readline())["url"]
        r = run([str(venv / "bin" / "articast-print"), url, "rec", "--frames", "5"],
                cwd=tmp_path, env={**os.environ, "PYTHONPATH": ""})
    finally:
        server.terminate()
        server.wait(30)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 5 and all(line.startswith("#") and " ok " in line for line in lines)
    # stopping after --frames leaves nothing of the connection pending (Python said "Task
    # was destroyed but it is pending!" on stderr)
    assert "pending" not in r.stderr and "Traceback" not in r.stderr, r.stderr

