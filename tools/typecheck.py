"""Run mypy on the packages as they are imported (``articast.core``, ``articast.service``, ...).

The import names live on the repository's top-level folders through setuptools' package-dir
(``articast.core`` is ``core/``): pip's editable install resolves them with an import hook that
static tools cannot see. This script writes the mapping as a tree of symbolic links,
``build/typecheck/articast/core -> ../../../core`` and so on, read from ``pyproject.toml``'s
``[tool.setuptools.package-dir]`` (nothing is copied, no stubs: mypy reads the sources), and
runs mypy with ``[tool.mypy]`` of ``pyproject.toml``, whose ``mypy_path`` names that tree.

    python tools/typecheck.py              # core and service (what .ci/run checks)
    python tools/typecheck.py -p articast.client

IDEs and other tools can use the same tree (``build/typecheck``) as an extra source root, or
the strict editable install (``pip install -e . --config-settings editable_mode=strict``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREE = ROOT / "build" / "typecheck"
DEFAULT = ("-p", "articast.core", "-p", "articast.service")


def link_tree() -> Path:
    """``build/typecheck/<import path>`` -> the folder setuptools maps it to."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    mapping = config["tool"]["setuptools"]["package-dir"]
    for name, folder in mapping.items():
        link = TREE.joinpath(*name.split("."))
        link.parent.mkdir(parents=True, exist_ok=True)
        target = os.path.relpath(ROOT / folder, link.parent)
        if link.is_symlink() and os.readlink(link) == target:
            continue
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(target, target_is_directory=True)
    return TREE


def main(argv: list[str]) -> int:
    link_tree()
    args = argv or list(DEFAULT)
    return subprocess.call([sys.executable, "-m", "mypy", *args], cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
