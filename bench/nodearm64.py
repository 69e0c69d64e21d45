"""Only the emulated arm64 vehicle node of :mod:`bench.node`: ``python -m bench nodearm64``.

``node.arm64_agent_pod_to_first_report_s`` and ``agent.rss_mb_arm64`` come from one arm64
fleet under qemu-user-static, which is slow and sensitive to the machine's load; run
alone, they need neither the three amd64 node starts nor the amd64 chart run before them
(same figures, same steps, on a control plane of their own). Build the images first
(``docker/build-images.sh``, or ``$ROOST_IMAGES_DIR`` naming archives built before) so
the measurement does not include an image build.
"""

from __future__ import annotations

from bench.core import Figure
from bench.node import arm64_run, measure


def run() -> list[Figure]:
    return measure((arm64_run,))
