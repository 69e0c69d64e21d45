"""`roost-sim fly`: a running simulated autopilot takes off when asked on its control socket.

The sandbox uses this as the stand-in for a mission's onboard controller (kwok only
pretends to run the onboard pod), so its vehicles are airborne when the fault hits and the
agent's arbiter, which only switches in flight, has something to do. Real processes: a
``roost-sim run`` streaming MAVLink over UDP to a socket this test holds, and the
``roost-sim`` CLI reaching it through its unix control socket.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.support.waiting import wait_until

BIN = Path(sys.executable).parent


def _sim(state_dir: Path, *args: str) -> dict[str, Any]:
    result = subprocess.run(
        [str(BIN / "roost-sim"), "--state-dir", str(state_dir), *args],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    answer: dict[str, Any] = json.loads(result.stdout)
    return answer


@pytest.fixture
def running_sims(tmp_path: Path) -> Iterator[Path]:
    """A ``roost-sim run`` with two PX4 autopilots streaming to a UDP socket we hold."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    config = tmp_path / "sims.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "autopilots": [
                    {"name": n, "stack": "px4", "sysid": i, "udp_out": f"127.0.0.1:{port}"}
                    for i, n in enumerate(("fc-a", "fc-b"), start=1)
                ]
            }
        )
    )
    state_dir = tmp_path / "sims"
    proc = subprocess.Popen(
        [str(BIN / "roost-sim"), "--state-dir", str(state_dir), "run", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        started = [json.loads(proc.stdout.readline()) for _ in range(2)]
        assert [s["name"] for s in started] == ["fc-a", "fc-b"]
        yield state_dir
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        listener.close()


def test_fly_arms_and_takes_off_only_the_named_autopilot(running_sims: Path) -> None:
    before = _sim(running_sims, "status", "fc-a")["state"]
    assert (before["armed"], before["landed_state"]) == (False, "OnGround")

    assert _sim(running_sims, "fly", "fc-a", "--altitude", "5")["ok"] is True

    def airborne() -> dict[str, Any] | None:
        state: dict[str, Any] = _sim(running_sims, "status", "fc-a")["state"]
        return state if state["landed_state"] == "InAir" and state["altitude_m"] > 4 else None

    state = wait_until("fc-a airborne above 4 m", airborne, 20.0)
    assert state["armed"] is True
    assert state["landed_state"] == "InAir"
    other = _sim(running_sims, "status", "fc-b")["state"]
    assert (other["armed"], other["landed_state"]) == (False, "OnGround")
