"""The follower's MAVLink side over real UDP on 127.0.0.1, against a scripted autopilot.

The autopilot here is a pymavlink endpoint that plays the few messages the follower
needs (heartbeat, position, command answers) and drops commands on purpose: what is
tested is the follower's resending, not a flight.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from pymavlink import mavutil
from syncpaths.vehicle import COMMAND_TRIES, MavlinkVehicle

ARM = mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
ACCEPTED = mavutil.mavlink.MAV_RESULT_ACCEPTED


class ScriptedAutopilot:
    """Answers a command only on its ``answer_on``-th copy; records every copy's
    confirmation field."""

    def __init__(self, answer_on: int) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            "udpin:127.0.0.1:0", source_system=1, source_component=1
        )
        self.port: int = self.conn.port.getsockname()[1]
        self.answer_on = answer_on
        self.confirmations: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() == "COMMAND_LONG" and msg.command == ARM:
                self.confirmations.append(msg.confirmation)
                if len(self.confirmations) == self.answer_on:
                    self.conn.mav.command_ack_send(ARM, ACCEPTED)
            if self.conn.address is None or time.monotonic() - last < 0.1:
                continue  # streams only once the follower has spoken (udpin)
            last = time.monotonic()
            self.conn.mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0
            )
            self.conn.mav.local_position_ned_send(0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.conn.close()


@pytest.fixture
def answered_on(request: pytest.FixtureRequest) -> Iterator[tuple[ScriptedAutopilot, Any]]:
    autopilot = ScriptedAutopilot(answer_on=request.param)
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{autopilot.port}")
    try:
        vehicle.wait_connected(timeout_s=10)
        yield autopilot, vehicle
    finally:
        vehicle.close()
        autopilot.stop()


@pytest.mark.parametrize("answered_on", [1, COMMAND_TRIES], indirect=True)
def test_a_lost_command_is_sent_again_with_its_confirmation_counted(
    answered_on: tuple[ScriptedAutopilot, MavlinkVehicle],
) -> None:
    autopilot, vehicle = answered_on
    assert vehicle._command(ARM, 1) == ACCEPTED
    assert autopilot.confirmations == list(range(autopilot.answer_on))


@pytest.mark.parametrize("answered_on", [COMMAND_TRIES + 1], indirect=True)
def test_a_command_never_answered_fails_after_its_tries(
    answered_on: tuple[ScriptedAutopilot, MavlinkVehicle],
) -> None:
    autopilot, vehicle = answered_on
    with pytest.raises(TimeoutError, match=f"in {COMMAND_TRIES} tries"):
        vehicle._command(ARM, 1)
    assert autopilot.confirmations == list(range(COMMAND_TRIES))
