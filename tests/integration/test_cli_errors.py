"""Every user error of ``roost`` is one line on stderr and a non-zero exit, never a traceback.

The real ``roost`` console script runs in a subprocess (no cluster is needed: each
command here fails on its command line before it would contact one), so what is checked
is exactly what a user sees. The option parsers behind them are tested in
``tests/unit/test_cli_main.py``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOST = Path(sys.executable).parent / "roost"


def run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {"PATH": str(ROOST.parent), "HOME": str(tmp_path), "KUBECONFIG": ""}
    return subprocess.run(
        [str(ROOST), "--sandbox-dir", str(tmp_path / "sandbox"), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=False,
    )


@pytest.mark.parametrize(
    ("args", "code", "says"),
    [
        (["status", "--interval", "inf"], 2, "'--interval': inf is not a number from 0.2 to 3600"),
        (["status", "--interval", "nan"], 2, "nan is not a number"),
        (["status", "--interval", "0.1"], 2, "0.1 is not a number from 0.2"),
        (["status", "--interval", "fast"], 2, "'fast' is not a number"),
        (["status", "--events", "100000"], 2, "--events"),
        (["estop", "--all", "--wait", "1e400"], 2, "'--wait': 1e400 is not a number"),
        (["estop", "--all", "--wait", "-inf"], 2, "-inf is not a number from 0 to 3600"),
        (["sandbox", "up", "--fault-after", "inf"], 2, "'--fault-after': inf"),
        (["sandbox", "up", "--vehicles", "0"], 2, "--vehicles"),
        (["sandbox", "up", "--trajectories", "."], 1, "add --mission"),
        (
            ["sandbox", "up", "--mission", "sync-paths", "--trajectories", "/no/trajectories"],
            1,
            "/no/trajectories is not a directory of trajectories",
        ),
        (["fault", "drone-1", "px4-a", "jitter", "--value", "inf"], 1, "jitter value 'inf'"),
        (["fault", "drone-1", "px4-a", "loss", "--value", "nan"], 1, "loss value 'nan'"),
        (["fault", "drone-1", "px4-a", "loss", "--value", "101"], 1, "from 0 to 100"),
        (["fault", "drone-1", "px4-a", "spoof", "--value", "1.5"], 1, "whole system id"),
        (["fault", "drone-1", "px4-a", "silence", "--value", "3"], 1, "silence takes no value"),
        (["fault", "drone-1", "px4-a", "sensor", "--value", "nope"], 1, "sensor 'nope'"),
        (["fault", "drone-1", "px4-a", "melt"], 1, "unknown fault 'melt'"),
        (["fault", "drone-1", "px4-a", "jitter", "--value", "20"], 1, "no sandbox is running"),
        (["abort"], 2, "Missing argument"),
        (["--no-such-option"], 2, "No such option"),
        (["estop", "--all"], 1, "no cluster"),
    ],
)
def test_a_user_error_is_one_line_and_a_non_zero_exit(
    tmp_path: Path, args: list[str], code: int, says: str
) -> None:
    result = run(tmp_path, *args)
    assert result.returncode == code, result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and says in lines[0]


def test_help_still_prints_and_exits_zero(tmp_path: Path) -> None:
    result = run(tmp_path, "status", "--help")
    assert result.returncode == 0 and "--interval" in result.stdout
