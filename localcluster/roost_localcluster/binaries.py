"""Where the control-plane binaries live, and building them when they are missing.

The binaries are built from the wrapper Go modules in ``localcluster/gomod`` by
``localcluster/build-control-plane.sh`` and cached under ``~/.cache/roost`` keyed by version.
That script is the one place that knows the versions and the cache layout; Python asks it
(``--print``) instead of repeating either.
"""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

PACKAGE_HOME = Path(__file__).resolve().parent.parent
REPO_ROOT = PACKAGE_HOME.parent
BUILD_SCRIPT = PACKAGE_HOME / "build-control-plane.sh"
COMPONENTS = ("etcd", "kube-apiserver", "kube-controller-manager", "kube-scheduler", "kwok")
KINE_GO_MOD = PACKAGE_HOME / "gomod" / "kine" / "go.mod"


def kine_version() -> str:
    """The kine version pinned in its wrapper module (the build records it in kine.version)."""
    for line in KINE_GO_MOD.read_text().splitlines():
        fields = line.split()
        if len(fields) >= 2 and fields[0] == "github.com/k3s-io/kine":
            return fields[1]
    raise RuntimeError(f"no github.com/k3s-io/kine requirement in {KINE_GO_MOD}")


def bin_dir() -> Path:
    """The cache directory holding (or about to hold) the binaries for the pinned versions."""
    out = subprocess.run(
        [str(BUILD_SCRIPT), "--print"], check=True, capture_output=True, text=True
    ).stdout
    return Path(out.strip())


def missing(directory: Path, names: tuple[str, ...] = COMPONENTS) -> list[str]:
    """Those of ``names`` not yet built into ``directory`` (or, for kine, of another version)."""
    result = [name for name in names if not (directory / name).is_file()]
    stamp = directory / "kine.version"
    stale = not stamp.is_file() or stamp.read_text().strip() != kine_version()
    if "kine" in names and "kine" not in result and stale:
        result.append("kine")
    return result


def ensure_built(names: tuple[str, ...] = COMPONENTS) -> Path:
    """Return the binary directory, building what of ``names`` is missing first.

    A warm cache returns at once; a cold build takes minutes and prints its progress to
    stderr (it is inherited, so pytest shows it with ``-s`` and always in its log).
    """
    directory = bin_dir()
    if missing(directory, names):
        subprocess.run(
            [str(BUILD_SCRIPT), *names], check=True, stdout=subprocess.DEVNULL, stderr=sys.stderr
        )
    still_missing = missing(directory, names)
    if still_missing:
        raise RuntimeError(f"build did not produce {still_missing} in {directory}")
    return directory


NODE_BUILD_SCRIPT = PACKAGE_HOME / "build-node.sh"
NODE_BINARIES = ("kubelet", "kube-proxy", "containerd", "ctr", "containerd-shim-runc-v2")
CNI_PLUGINS = ("bridge", "host-local", "loopback", "portmap")
PAUSE_ARCHIVE = "images/roost-pause.oci.tar"
PAUSE_NAME = "images/roost-pause.name"  # the image name, tagged with a digest of its sources


HOST_ARCH = {"x86_64": "amd64", "aarch64": "arm64"}.get(platform.machine(), platform.machine())
"""This machine's architecture as Go and Kubernetes name it (``kubernetes.io/arch``)."""


def node_dir(arch: str = HOST_ARCH) -> Path:
    """The cache directory of a real node's programs for ``arch`` (``build-node.sh`` lays
    it out; another architecture's has its own)."""
    out = subprocess.run(
        [str(NODE_BUILD_SCRIPT), "--arch", arch, "--print"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return Path(out.strip())


def node_missing(directory: Path) -> list[str]:
    """What of a real node's programs and pause image is not yet in ``directory``."""
    wanted = [f"bin/{n}" for n in NODE_BINARIES] + [f"cni/{n}" for n in CNI_PLUGINS]
    wanted += [PAUSE_ARCHIVE, PAUSE_NAME]
    return [path for path in wanted if not (directory / path).is_file()]


def pause_image(directory: Path) -> str:
    """The name of the pause image built into ``directory`` (its sandbox image)."""
    return (directory / PAUSE_NAME).read_text().strip()


def ensure_node_built(arch: str = HOST_ARCH) -> Path:
    """Return the node directory for ``arch``, building what is missing first (minutes
    when cold)."""
    directory = node_dir(arch)
    if node_missing(directory):
        subprocess.run(
            [str(NODE_BUILD_SCRIPT), "--arch", arch],
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=sys.stderr,
        )
    still_missing = node_missing(directory)
    if still_missing:
        raise RuntimeError(f"build did not produce {still_missing} in {directory}")
    return directory
