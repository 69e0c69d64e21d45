"""Where the control-plane binaries live, and building them when they are missing.

The binaries are built from the wrapper Go modules in ``localcluster/gomod`` by
``localcluster/build-control-plane.sh`` and cached under ``~/.cache/roost`` keyed by version.
That script is the one place that knows the versions and the cache layout; Python asks it
(``--print``) instead of repeating either.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PACKAGE_HOME = Path(__file__).resolve().parent.parent
REPO_ROOT = PACKAGE_HOME.parent
BUILD_SCRIPT = PACKAGE_HOME / "build-control-plane.sh"
COMPONENTS = ("etcd", "kube-apiserver", "kube-controller-manager", "kube-scheduler", "kwok")


def bin_dir() -> Path:
    """The cache directory holding (or about to hold) the binaries for the pinned versions."""
    out = subprocess.run(
        [str(BUILD_SCRIPT), "--print"], check=True, capture_output=True, text=True
    ).stdout
    return Path(out.strip())


def missing(directory: Path) -> list[str]:
    """Names of the components not yet built into ``directory``."""
    return [name for name in COMPONENTS if not (directory / name).is_file()]


def ensure_built() -> Path:
    """Return the binary directory, building what is missing first.

    A warm cache returns at once; a cold build takes minutes and prints its progress to
    stderr (it is inherited, so pytest shows it with ``-s`` and always in its log).
    """
    directory = bin_dir()
    if missing(directory):
        subprocess.run(
            [str(BUILD_SCRIPT)], check=True, stdout=subprocess.DEVNULL, stderr=sys.stderr
        )
    still_missing = missing(directory)
    if still_missing:
        raise RuntimeError(f"build did not produce {still_missing} in {directory}")
    return directory
