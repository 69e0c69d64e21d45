"""The steps of docker/Dockerfile that run inside the image, in Python rather than shell.

Why Python: the base then needs nothing but ``python3``. The local base (docker/
build-base.sh) has no coreutils, findutils or bash (30 MB the images never use), and any
public Python base works the same way. Two steps:

``dependencies WHEELS`` and ``roost WHEELS`` (build stages, in that order): a virtualenv at
/opt/roost with Roost's dependencies, then Roost itself, installed from the wheels built
on the host by pip run from its own wheel (a zip archive Python can execute; the base
needs no pip). Two steps so that a change to Roost's sources rebuilds only the second:
the first (the dependencies, most of the image and most of the build time, several
minutes for arm64 under emulation) stays a cached layer while its wheels are unchanged.
Both make what they install small and ready for a read-only root:

1. What never runs in a pod is left out: the ``roost`` CLI and the local control plane
   (they run on a workstation; the control plane needs Go-built binaries no image has),
   with the distributions only they use (the CLI's typer, rich and pygments, the
   certificate authority's cryptography: 25 MB, never installed); ``kubernetes.aio`` (an
   asyncio copy of the whole client, 41 MB; kopf talks to the API with aiohttp), lxml
   (only pymavlink's code generator needs it), pymavlink's generator, log indexer and
   every MAVLink dialect but the ones Roost speaks (v2 ``ardupilotmega`` for the agent;
   ``common`` and ``all`` for the simulator, which sends PX4's CURRENT_MODE, a message
   only ``all`` defines), and third-party test modules.
2. Everything is compiled ahead of time: without bytecode, importing the Kubernetes
   client, kopf and the dialect takes several seconds at each start instead of under one,
   and nothing can be written at run time. Docstrings stay: the Kubernetes client's watch
   reads return types from them.
3. Sources are kept only for Roost's own packages (readable tracebacks where bugs are
   likely ours); third-party modules are kept as bytecode only (``foo.pyc`` where
   ``foo.py`` was, which Python imports directly). Source plus bytecode of the Kubernetes
   client alone would be 60 MB.

``harden`` (final stage): strips setuid/setgid bits from the whole root filesystem (the
agent container is privileged on hardware, where allowPrivilegeEscalation cannot be
false) and adds the ``roost`` user and group (65532, the chart's runAsUser) to
/etc/passwd and /etc/group, so tools that look the uid up find a name.
"""

from __future__ import annotations

import compileall
import os
import py_compile
import shutil
import stat
import subprocess
import sys
from pathlib import Path

PREFIX = Path("/opt/roost")
PYTHON = PREFIX / "bin/python3"
UNUSED = (
    "kubernetes/aio",
    "lxml",
    "pymavlink/generator",
    "pymavlink/dfindexer",
    "pymavlink/dialects/v10",
    "websocket/tests",
    "certifi/tests",
)
WORKSTATION_ONLY = ("roost_cli", "roost_localcluster", "bin/roost", "bin/roost-cluster")
WORKSTATION_DISTRIBUTIONS = (
    "typer", "rich", "pygments", "markdown-it-py", "mdurl", "shellingham", "annotated-doc",
    "cryptography", "cffi", "pycparser", "psutil",
)  # fmt: skip
UNUSED_GLOBS = ("lxml-*.dist-info", "kubernetes/**/*_test.py", "kubernetes/**/test_*.py")
DIALECTS_KEPT = {"__init__.py", "common.py", "ardupilotmega.py", "all.py"}
OWN_PREFIX = "roost_"
MODE = py_compile.PycInvalidationMode.UNCHECKED_HASH
UID = GID = 65532
PIP_OPTIONS = (
    "--quiet", "--no-index", "--no-compile", "--no-cache-dir", "--disable-pip-version-check",
)  # fmt: skip


def dependencies(wheels: Path) -> None:
    """Roost's dependencies (every wheel in ``wheels`` but pip's and the workstation's)."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(PREFIX)], check=True)
    kept = sorted(
        str(wheel)
        for wheel in wheels.glob("*.whl")
        if distribution(wheel) not in {"pip", *WORKSTATION_DISTRIBUTIONS}
    )
    subprocess.run([*pip(wheels), "install", *PIP_OPTIONS, "--no-deps", *kept], check=True)
    site = site_packages()
    remove_unused(site, UNUSED, UNUSED_GLOBS)
    remove_unspoken_dialects(site)
    compile_dependencies(site)


def roost(wheels: Path, pip_wheels: Path) -> None:
    """Roost's own wheel onto the dependencies; its workstation-only parts removed."""
    (wheel,) = wheels.glob("roost-*.whl")
    subprocess.run([*pip(pip_wheels), "install", *PIP_OPTIONS, "--no-deps", str(wheel)], check=True)
    site = site_packages()
    remove_unused(site, WORKSTATION_ONLY, ())
    for top in sorted(site.glob(f"{OWN_PREFIX}*")):
        if top.is_dir() and not compileall.compile_dir(
            top, quiet=1, workers=0, invalidation_mode=MODE
        ):
            sys.exit(f"image: compiling {top} failed")


def pip(wheels: Path) -> list[str]:
    """pip run from its own wheel in ``wheels`` by the virtualenv's Python."""
    (pip_wheel,) = wheels.glob("pip-*.whl")
    return [str(PYTHON), str(pip_wheel / "pip")]


def distribution(wheel: Path) -> str:
    """A wheel's distribution name, normalised (``Markdown_It_Py`` → ``markdown-it-py``)."""
    return wheel.name.split("-", 1)[0].lower().replace("_", "-").replace(".", "-")


def site_packages() -> Path:
    return Path(
        subprocess.run(
            [str(PYTHON), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )


def remove_unused(site: Path, paths: tuple[str, ...], patterns: tuple[str, ...]) -> None:
    """Delete ``paths`` (``bin/...`` under the prefix, the rest under site-packages) and
    what ``patterns`` match under site-packages."""
    for rel in paths:
        path = PREFIX / rel if rel.startswith("bin/") else site / rel
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    for pattern in patterns:
        for path in site.glob(pattern):
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()


def remove_unspoken_dialects(site: Path) -> None:
    """Every MAVLink dialect module but the ones Roost speaks (before compiling: the
    names kept are the sources')."""
    for path in (site / "pymavlink/dialects/v20").iterdir():
        if path.is_file() and path.name not in DIALECTS_KEPT:
            path.unlink()


def compile_dependencies(site: Path) -> None:
    """Bytecode for every third-party module, then its source removed. A module that does
    not compile (a Python 2 leftover nobody imports) simply keeps its source."""
    for top in sorted(site.iterdir()):
        if top.is_dir():
            compileall.compile_dir(top, quiet=2, legacy=True, workers=0, invalidation_mode=MODE)
        elif top.suffix == ".py":
            compileall.compile_file(top, quiet=2, legacy=True, invalidation_mode=MODE)
    for source in site.rglob("*.py"):
        if source.with_suffix(".pyc").is_file():
            source.unlink()


def harden() -> None:
    root_dev = Path("/").lstat().st_dev
    for walked, dirs, files in os.walk("/"):  # Path.walk needs Python 3.12
        top = Path(walked)
        # Stay on the root filesystem (no /proc, /sys or bind mounts of the build).
        dirs[:] = [d for d in dirs if (top / d).lstat().st_dev == root_dev]
        for name in files:
            path = top / name
            mode = path.lstat().st_mode
            if stat.S_ISREG(mode) and mode & (stat.S_ISUID | stat.S_ISGID):
                path.chmod(stat.S_IMODE(mode) & ~(stat.S_ISUID | stat.S_ISGID))
    with Path("/etc/passwd").open("a") as passwd:
        passwd.write(f"roost:x:{UID}:{GID}:roost:/nonexistent:/usr/sbin/nologin\n")
    with Path("/etc/group").open("a") as group:
        group.write(f"roost:x:{GID}:\n")


def main() -> None:
    match sys.argv[1:]:
        case ["dependencies", wheels]:
            dependencies(Path(wheels))
        case ["roost", wheels, pip_wheels]:
            roost(Path(wheels), Path(pip_wheels))
        case ["harden"]:
            harden()
        case _:
            sys.exit("usage: image.py dependencies WHEELS | roost WHEELS PIP_WHEELS | harden")


if __name__ == "__main__":
    main()
