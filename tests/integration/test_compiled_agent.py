"""The agent's suites, run against the build the image ships.

The image's wheel has the agent's per-message path compiled by mypyc (``setup.py``). A
compiled module checks its annotations at run time and its classes refuse attributes
they do not declare, so a wrong annotation on the message path would drop messages in
the image while the interpreted checkout passed every test. This test builds that wheel
(``docker/build-images.sh --compiled-tree``, cached), then runs the suites that drive the
compiled modules in a pytest of their own with the compiled build first on
``PYTHONPATH``; ``tests/conftest.py`` fails that run unless each compiled module really
imports from it. Tests that put stand-ins into a compiled class are marked
``interpreted_only`` and skip there.

The compiled run keeps the interpreted run's two tiers: its tests not marked ``serial``
run in this file's ``parallel`` case, beside the other files of the parallel pass (as
they do interpreted), and its ``serial`` tests in the ``serial`` case, alone in the
serial pass (they judge real time). Each message path runs once against the compiled
build; ``SUITES`` (tests/support/compiled.py) says which cases are left to the
interpreted run and why. In ``make test`` the interpreted passes leave the integration
tests listed there to this run (``--leave-to-compiled``), so each of them runs once.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from roost_localcluster.binaries import REPO_ROOT
from tests.support.compiled import SUITES, compiled_modules, compiled_tree, environment

TIERS = [
    # the suites' tests that wait, beside the other files of the parallel pass
    pytest.param("not serial", id="parallel"),
    # serial: the suites' tests that judge real time, alone in the serial pass
    pytest.param("serial", id="serial", marks=pytest.mark.serial),
]


@pytest.mark.slow
@pytest.mark.timeout(1500)
@pytest.mark.parametrize("tier", TIERS)
def test_the_agent_suites_pass_against_the_compiled_build(tier: str) -> None:
    tree = compiled_tree()
    assert {
        "roost_mavlink.codec",
        "roost_agent.health",
        "roost_agent.transport",
        "roost_agent.trust",
        "roost_agent.reader",
        "roost_agent.link",
        "roost_agent.hub",
        "roost_agent._udpbatch",
    } <= set(compiled_modules(tree))
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-m", tier, *SUITES],
        cwd=REPO_ROOT,
        env={**_without_pytest_state(), **environment(tree)},
        capture_output=True,
        text=True,
        check=False,
        timeout=1500,
    )
    report = run.stdout[-6000:] + run.stderr[-2000:]
    assert run.returncode == 0, report
    assert "compiled (mypyc): " in run.stdout, report  # the header tests/conftest.py writes


def _without_pytest_state() -> dict[str, str]:
    """This process's environment without what pytest set for its own run."""
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
