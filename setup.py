"""Packaging hook: with ``ROOST_COMPILE=1`` the agent's per-message path is compiled.

Every datagram an autopilot sends passes through the MAVLink parser
(``roost_mavlink.codec``), the link's modules that read, trust and account for it
(``roost_agent.transport``, ``roost_agent.reader``, ``roost_agent.trust``,
``roost_agent.link``), the health tracker that judges it (``roost_agent.health``) and
the hub that routes it to clients (``roost_agent.hub``).
They are mypy-strict, so mypyc can compile them to C extension modules that run the same
code cheaper (``agent.cpu_ms_per_10k_msgs`` against ``agent.cpu_ms_per_10k_msgs_interpreted``
in the README's benchmark table). The image build sets ``ROOST_COMPILE=1``
(docker/build-images.sh); an editable install for development keeps those modules
interpreted, and the test suite runs the agent's suites against the compiled build as
well (tests/integration/test_compiled_agent.py). The hand-written C extension
(``agent/roost_agent/_udpbatch.c``: batch reads and the hub's fast path) is built in
every install on Linux, the editable one included.

Compiling needs mypy (the ``dev`` extra) and a C compiler with Python's headers, so the
wheel is built without build isolation: ``ROOST_COMPILE=1 pip wheel --no-build-isolation .``
"""

from __future__ import annotations

import os
import sys
from typing import Any

from setuptools import Extension, setup

COMPILED_MODULES = (
    "mavlink/roost_mavlink/codec.py",
    "agent/roost_agent/health.py",
    "agent/roost_agent/transport.py",
    "agent/roost_agent/trust.py",
    "agent/roost_agent/reader.py",
    "agent/roost_agent/link.py",
    "agent/roost_agent/hub.py",
)
"""The modules compiled with ``ROOST_COMPILE=1``, as paths from the repository root."""


def _ext_modules() -> list[Any]:
    compiling = os.environ.get("ROOST_COMPILE") == "1"
    native = c_extensions(required=compiling) if sys.platform == "linux" else []
    if not compiling:
        return native
    # Only here: mypy is a build tool, not a dependency.
    from mypyc.build import mypycify  # noqa: PLC0415

    return [*mypycify(list(COMPILED_MODULES), opt_level="3"), *native]


def c_extensions(*, required: bool) -> list[Extension]:
    """The hand-written C extension modules (Linux only), built in every install, an
    editable one included: the agent a developer starts from the checkout routes and
    reads as the images' does. ``required``: a failed build fails the install (the
    compiled wheel); otherwise it is skipped with a warning and the agent reads and
    routes in Python."""
    return [
        # recvmmsg with kernel arrival stamps for the UDP links (roost_agent.transport
        # falls back to Python reads without it), and the hub's fast path: the active
        # autopilot's frames routed to plain UDP clients in C (roost_agent.fastpath;
        # without it, in Python)
        Extension(
            "roost_agent._udpbatch", ["agent/roost_agent/_udpbatch.c"], optional=not required
        ),
    ]


setup(ext_modules=_ext_modules())
