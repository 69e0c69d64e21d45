"""``roost dashboard`` as a child process on a free port, for the dashboard's tests."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.support.waiting import wait_until

ROOST = Path(sys.executable).parent / "roost"
ANNOUNCE = re.compile(r"Roost dashboard on (http://\S+/)")


@contextmanager
def running_dashboard(log: Path, *args: str) -> Iterator[str]:
    """``roost [ARGS before "dashboard"] dashboard --port 0 [the rest]``; its URL.

    ``args`` up to and including ``--kubeconfig PATH`` go before the command, the rest
    after it. Its output goes to ``log``; no traceback may appear there."""
    split = args.index("--kubeconfig") + 2 if "--kubeconfig" in args else 0
    with log.open("w") as out:
        proc = subprocess.Popen(
            [str(ROOST), *args[:split], "dashboard", "--port", "0", *args[split:]],
            stdout=out,
            stderr=subprocess.STDOUT,
            text=True,
            env={"COLUMNS": "400", "PATH": str(ROOST.parent)},
        )
    try:

        def announced() -> str | None:
            assert proc.poll() is None, log.read_text()
            found = ANNOUNCE.search(log.read_text())
            return found.group(1) if found else None

        yield wait_until("the dashboard's URL", announced, 30, 0.1)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert "Traceback" not in log.read_text()
