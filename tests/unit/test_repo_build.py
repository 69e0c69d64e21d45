"""The checkout's own install: what `make setup` builds besides the Python packages.

Every install builds the hand-written C extension (``setup.py``, ``c_extensions``), the
editable one included, so an agent started from the checkout (``make demo``, a
developer's ``roost-agent``, a measurement that runs ``.venv/bin/roost-agent``) reads in
batches and routes the hub's frames in C as the images' agent does. Outside the compiled
wheel the build is optional: a machine without a C compiler gets an agent that reads and
routes in Python, with a warning in pip's log. This checks that a machine with a compiler
got the extension, so a C file that stops compiling cannot pass unnoticed as that
fallback.
"""

from __future__ import annotations

import importlib.util
import shutil
import sys

import pytest


def test_an_install_on_a_machine_with_a_c_compiler_built_the_c_extension() -> None:
    if sys.platform != "linux" or not (shutil.which("cc") or shutil.which("gcc")):
        pytest.skip("no C compiler here: the install skipped the C extension (setup.py)")
    found = importlib.util.find_spec("roost_agent._udpbatch")
    assert found is not None, (
        "roost_agent._udpbatch is not built: `make setup` (or `.venv/bin/pip install -e . "
        "--no-deps`) builds it; a failed build is in .venv/pip.log"
    )
