"""Image figures: the size of the operator and agent images, and a warm ``make images``.

- ``images.agent_mb`` / ``images.operator_mb``: uncompressed size of each image's amd64
  build as podman reports it after loading it from the OCI archive ``make images``
  exported (what a node's disk holds once the image is imported); the archive's
  (compressed, both platforms) size is in the note.
- ``images.agent_mb_arm64`` / ``images.operator_mb_arm64``: the same for the arm64 build
  in the same archive (the image index's other platform: what a Raspberry Pi holds).
- ``images.build_cold_multiarch_s``: the last build of both platforms from an empty cache
  (the Debian bases made too), as ``build-times.tsv`` beside the archives records it.
- ``images.build_warm_s``: ``docker/build-images.sh`` with everything cached (sources
  unchanged), median of three: what ``make images`` costs on every ``make test``. The
  last cold build's time (from ``build-times.tsv`` beside the archives) is in its note.

Needs buildah and podman (``make images`` installs them on Debian); without them this
module reports nothing.
"""

from __future__ import annotations

import csv
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from bench.core import Figure
from tests.support.images import (
    ARCHS,
    BUILD_SCRIPT,
    TARGETS,
    Podman,
    archive,
    build_images,
    missing_tools,
)

COMMAND = "python -m bench images"


def _builds(images_dir: Path) -> list[list[str]]:
    """The rows of ``build-times.tsv``: images, seconds, when[, archs, cold|warm]."""
    record = images_dir / "build-times.tsv"
    if not record.exists():
        return []
    with record.open() as f:
        return [row for row in csv.reader(f, delimiter="\t") if row and row[0] == "images"]


def _last_cold_build_s(images_dir: Path) -> int | None:
    rows = _builds(images_dir)
    return int(rows[-1][1]) if rows else None


def cold_multiarch(images_dir: Path) -> list[Figure]:
    rows = [r for r in _builds(images_dir) if r[3:] == [" ".join(ARCHS), "cold"]]
    if not rows:
        return []
    _, seconds, when, *_ = rows[-1]
    return [
        Figure(
            "images.build_cold_multiarch_s",
            float(seconds),
            "s",
            "informational",
            "rm -rf ~/.cache/roost/images && docker/build-images.sh",
            note=f"both platforms from an empty image cache ({when}): Debian bases (arm64 "
            "under qemu), wheels (arm64 per-message path cross-compiled), both targets per "
            "platform (arm64 RUN steps under qemu), two image indexes",
        )
    ]


def sizes(images_dir: Path) -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory(prefix="bench-images-") as tmp:
        podman = Podman(Path(tmp))
        try:
            for arch in ARCHS:
                suffix = "" if arch == "amd64" else f"_{arch}"
                for target in TARGETS:
                    oci = archive(images_dir, target)
                    size = podman.inspect(podman.load(oci, arch))["Size"]
                    target_text = "<= 150" if target == "agent" else "informational"
                    figures.append(
                        Figure(
                            f"images.{target}_mb{suffix}",
                            size / 1e6,
                            "MB",
                            target_text,
                            COMMAND,
                            note=f"linux/{arch}, uncompressed, local Debian base; OCI "
                            f"archive (both platforms) {oci.stat().st_size / 1e6:.0f} MB",
                        )
                    )
        finally:
            podman.reset()
    return figures


def warm_build() -> Figure:
    times = []
    for _ in range(3):
        started = time.monotonic()
        subprocess.run([str(BUILD_SCRIPT)], check=True, capture_output=True, timeout=600)
        times.append(time.monotonic() - started)
    cold = _last_cold_build_s(build_images())
    cold_text = (
        f"; last rebuild {cold} s (wheels and both images; a cold cache adds about a minute "
        "for the Debian base)"
        if cold
        else ""
    )
    return Figure(
        "images.build_warm_s",
        statistics.median(times),
        "s",
        "<= 5",
        COMMAND,
        note=f"median of {[round(t, 2) for t in times]}{cold_text}",
    )


def run() -> list[Figure]:
    if missing_tools():
        print(f"bench images: skipped, missing {missing_tools()}")
        return []
    images_dir = build_images()
    return [*sizes(images_dir), warm_build(), *cold_multiarch(images_dir)]
