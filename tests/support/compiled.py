"""Roost's compiled build, as the images ship it, run from this checkout.

The image build compiles the agent's per-message path with mypyc (``setup.py``,
``ROOST_COMPILE=1``); ``docker/build-images.sh --compiled-tree`` installs the packages of
that same wheel that hold compiled modules (``roost_agent``, ``roost_mavlink``) into a
cached directory of its own. Putting the directory first on ``PYTHONPATH`` makes a
Python process (an agent started by a test or a benchmark, or a whole pytest run) import
those packages from it, compiled modules included, and everything else from the
checkout.

A run that means to test or measure the compiled build says so with
``ROOST_COMPILED_TREE`` (the directory); :func:`check_compiled_imports` then fails it
when any module the tree holds compiled was imported from elsewhere, so a stale path can
never pass the pure-Python modules off as the compiled ones.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from pathlib import Path

from tests.support.images import run_build_script

TREE_VARIABLE = "ROOST_COMPILED_TREE"


def compiled_tree() -> Path:
    """Build Roost's compiled wheel into the cache unless it is current; its directory."""
    return run_build_script("--compiled-tree", timeout_s=900)


def compiled_modules(tree: Path) -> list[str]:
    """Dotted names of the Roost modules ``tree`` holds as extension modules."""
    names = []
    for library in sorted(tree.glob("roost_*/**/*.so")):
        relative = library.relative_to(tree)
        stem = relative.name.split(".", 1)[0]
        names.append(".".join([*relative.parent.parts, stem]))
    return names


def environment(tree: Path) -> Mapping[str, str]:
    """Variables that make a child Python process run Roost from ``tree``."""
    path = os.environ.get("PYTHONPATH", "")
    return {
        "PYTHONPATH": f"{tree}{os.pathsep}{path}" if path else str(tree),
        TREE_VARIABLE: str(tree),
    }


def check_compiled_imports() -> list[str]:
    """With ``ROOST_COMPILED_TREE`` set, the compiled modules as imported; else nothing.

    Raises ``RuntimeError`` when the tree holds no compiled module, or when one of them
    imports from anywhere but the tree as its extension module.
    """
    root = os.environ.get(TREE_VARIABLE)
    if not root:
        return []
    tree = Path(root).resolve()
    names = compiled_modules(tree)
    if not names:
        raise RuntimeError(f"{tree} holds no compiled Roost module")
    for name in names:
        origin = Path(importlib.import_module(name).__file__ or "").resolve()
        if origin.suffix != ".so" or not origin.is_relative_to(tree):
            raise RuntimeError(f"{name} was imported from {origin}, not compiled from {tree}")
    return names
