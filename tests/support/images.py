"""Roost's container images as tests and benchmarks use them: build, load, run.

``docker/build-images.sh`` (``make images``) builds the operator and agent images with
buildah and exports them as OCI archives under ``~/.cache/roost/images``; it is cached,
so calling :func:`build_images` from a test costs nothing when ``make images`` ran first.
:class:`Podman` runs those archives in a private, throw-away image store (never the
machine's default one), with the flags a host without systemd and with low hard limits
needs: the same ones docker/buildah.sh uses.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roost_localcluster.binaries import HOST_ARCH, REPO_ROOT

BUILD_SCRIPT = REPO_ROOT / "docker" / "build-images.sh"
TOOLS = ("buildah", "podman", "runc", "mmdebstrap")
TARGETS = ("operator", "agent")
ARCHS = ("amd64", "arm64")
"""The platforms of every image index ``make images`` writes (linux/<arch>)."""
BINFMT_SCRIPT = REPO_ROOT / "docker" / "binfmt.sh"


def missing_tools() -> list[str]:
    """The image tools not on PATH (``make images`` installs them on Debian)."""
    return [tool for tool in TOOLS if shutil.which(tool) is None]


def emulation_missing(arch: str) -> str:
    """Why ``arch`` programs cannot run here ("" when they can: this machine's own, or
    another under qemu-user-static registered with binfmt_misc by docker/binfmt.sh)."""
    if arch == HOST_ARCH:
        return ""
    done = subprocess.run(
        [str(BINFMT_SCRIPT), "--check"], capture_output=True, text=True, check=False, timeout=60
    )
    return done.stderr.strip() if done.returncode else ""


def run_build_script(*args: str, timeout_s: float = 1800) -> Path:
    """Run ``docker/build-images.sh`` with ``args``; the directory it prints last."""
    done = subprocess.run(
        [str(BUILD_SCRIPT), *args], check=False, capture_output=True, text=True, timeout=timeout_s
    )
    if done.returncode != 0:
        command = " ".join([str(BUILD_SCRIPT), *args])
        raise RuntimeError(f"{command} failed:\n{done.stderr[-3000:]}")
    return Path(done.stdout.strip().splitlines()[-1])


def build_images() -> Path:
    """Build both images unless cached; the directory holding ``roost-<target>.oci.tar``.

    ``$ROOST_IMAGES_DIR`` names a directory of archives built before (of this checkout)
    to use instead, e.g. a copy taken while other checkouts rebuild the shared cache.
    """
    given = os.environ.get("ROOST_IMAGES_DIR")
    if given:
        return Path(given)
    return run_build_script()


def archive(images_dir: Path, target: str) -> Path:
    return images_dir / f"roost-{target}.oci.tar"


@dataclass(frozen=True)
class Podman:
    """podman on an image store under ``root``; :meth:`reset` drops it.

    Its run root (locks, container state) is a short directory of its own in the system's
    temporary directory: podman refuses a run root longer than 50 characters, which a
    store under pytest's per-worker temporary directories exceeds."""

    root: Path

    @property
    def runroot(self) -> Path:
        digest = hashlib.sha256(str(self.root.resolve()).encode()).hexdigest()[:12]
        return Path(tempfile.gettempdir()) / f"podman-{digest}"

    def reset(self) -> None:
        """Remove every image and container of the store, and its run root."""
        self.call("system", "reset", "--force")
        shutil.rmtree(self.runroot, ignore_errors=True)

    def command(self, *args: str) -> list[str]:
        return [
            "podman",
            "--root", str(self.root / "storage"),
            "--runroot", str(self.runroot),
            "--storage-driver", "vfs",
            "--runtime", "runc",
            "--cgroup-manager", "cgroupfs",
            "--events-backend", "file",
            *args,
        ]  # fmt: skip

    def call(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            self.command(*args), check=False, capture_output=True, text=True, timeout=timeout
        )

    def load(self, oci_archive: Path, arch: str = HOST_ARCH) -> str:
        """Load the ``arch`` image of an OCI archive (an image index: ``make images``
        writes amd64 and arm64); the image's ID."""
        done = self.call("pull", "--quiet", "--arch", arch, f"oci-archive:{oci_archive}")
        if done.returncode != 0:
            raise RuntimeError(f"podman pull --arch {arch} {oci_archive} failed: {done.stderr}")
        return done.stdout.strip().splitlines()[-1]

    def inspect(self, image: str) -> dict[str, Any]:
        done = self.call("image", "inspect", image)
        if done.returncode != 0:
            raise RuntimeError(f"podman image inspect {image} failed: {done.stderr}")
        return json.loads(done.stdout)[0]  # type: ignore[no-any-return]

    def run(
        self, image: str, *args: str, entrypoint: str | None = None
    ) -> subprocess.CompletedProcess[str]:
        """``podman run`` as the chart runs the pods: read-only root, no network."""
        options = [
            "--rm", "--read-only", "--network", "none",
            "--ulimit", "nofile=20000:20000", "--ulimit", "nproc=30000:30000",
        ]  # fmt: skip
        if entrypoint is not None:
            options += ["--entrypoint", entrypoint]
        return self.call("run", *options, image, *args)
