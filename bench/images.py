"""Image figures: the size of the operator and agent images, and a warm ``make images``.

- ``images.agent_mb`` / ``images.operator_mb``: uncompressed size of each image as podman
  reports it after loading the OCI archive ``make images`` exported (what a node's disk
  holds once the image is imported); the archive's (compressed) size is in the note.
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
from tests.support.images import BUILD_SCRIPT, TARGETS, Podman, archive, build_images, missing_tools

COMMAND = "python -m bench images"


def _last_cold_build_s(images_dir: Path) -> int | None:
    record = images_dir / "build-times.tsv"
    if not record.exists():
        return None
    with record.open() as f:
        rows = [row for row in csv.reader(f, delimiter="\t") if row and row[0] == "images"]
    return int(rows[-1][1]) if rows else None


def sizes(images_dir: Path) -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory(prefix="bench-images-") as tmp:
        podman = Podman(Path(tmp))
        try:
            for target in TARGETS:
                oci = archive(images_dir, target)
                size = podman.inspect(podman.load(oci))["Size"]
                target_text = "<= 150" if target == "agent" else "informational"
                figures.append(
                    Figure(
                        f"images.{target}_mb",
                        size / 1e6,
                        "MB",
                        target_text,
                        COMMAND,
                        note=f"uncompressed, local Debian base; OCI archive "
                        f"{oci.stat().st_size / 1e6:.0f} MB",
                    )
                )
        finally:
            podman.call("system", "reset", "--force")
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
    return [*sizes(images_dir), warm_build()]
