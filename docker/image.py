"""The steps of docker/Dockerfile that run inside the image, in Python rather than shell.

Why Python: the base then needs nothing but ``python3``. The local base (docker/
build-base.sh) has no coreutils, findutils or bash (30 MB the images never use), and any
public Python base works the same way. Two steps:

``install WHEELS`` (build stage): a virtualenv at /opt/roost with Roost installed from the
wheels built on the host, by pip run from its own wheel (a zip archive Python can
execute; the base needs no pip). Then it is made small and ready for a read-only root:

1. What never runs in a pod is removed: the ``roost`` CLI and the local control plane
   (they run on a workstation; the control plane needs Go-built binaries no image has),
   with the distributions only they use (the CLI's typer, rich and pygments, the
   certificate authority's cryptography: 25 MB); ``kubernetes.aio`` (an asyncio copy of the whole
   client, 41 MB; kopf talks to the API with aiohttp), lxml (only pymavlink's code
   generator needs it), pymavlink's generator, log indexer and every MAVLink dialect but
   the ones Roost speaks (v2 ``ardupilotmega`` for the agent; ``common`` and ``all`` for
   the simulator, which sends PX4's CURRENT_MODE, a message only ``all`` defines), and
   third-party test modules.
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


def install(wheels: Path) -> None:
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(PREFIX)], check=True)
    (pip_wheel,) = wheels.glob("pip-*.whl")
    pip = [str(PYTHON), str(pip_wheel / "pip"), "install", "--quiet", "--no-index"]
    options = ["--no-compile", "--no-cache-dir", "--disable-pip-version-check"]
    subprocess.run([*pip, *options, "--find-links", str(wheels), "roost"], check=True)
    uninstall = [str(PYTHON), str(pip_wheel / "pip"), "uninstall", "--quiet", "--yes"]
    subprocess.run([*uninstall, *WORKSTATION_DISTRIBUTIONS], check=True)
    site = Path(
        subprocess.run(
            [str(PYTHON), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    remove_unused(site)
    compile_all(site)


def remove_unused(site: Path) -> None:
    for rel in WORKSTATION_ONLY:
        path = PREFIX / rel if rel.startswith("bin/") else site / rel
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    for rel in UNUSED:
        shutil.rmtree(site / rel, ignore_errors=True)
    for pattern in UNUSED_GLOBS:
        for path in site.glob(pattern):
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()
    for path in (site / "pymavlink/dialects/v20").iterdir():
        if path.is_file() and path.name not in DIALECTS_KEPT:
            path.unlink()


def compile_all(site: Path) -> None:
    # A third-party module that does not compile (a Python 2 leftover nobody imports)
    # simply keeps its source; Roost's own must compile.
    for top in sorted(site.iterdir()):
        if top.name.startswith(OWN_PREFIX):
            if not compileall.compile_dir(top, quiet=1, workers=0, invalidation_mode=MODE):
                sys.exit(f"image: compiling {top} failed")
        elif top.is_dir():
            compileall.compile_dir(top, quiet=2, legacy=True, workers=0, invalidation_mode=MODE)
        elif top.suffix == ".py":
            compileall.compile_file(top, quiet=2, legacy=True, invalidation_mode=MODE)
    for source in site.rglob("*.py"):
        own = source.relative_to(site).parts[0].startswith(OWN_PREFIX)
        if not own and source.with_suffix(".pyc").is_file():
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
        case ["install", wheels]:
            install(Path(wheels))
        case ["harden"]:
            harden()
        case _:
            sys.exit("usage: image.py install WHEELS | harden")


if __name__ == "__main__":
    main()
