"""AUTOPILOT_VERSION read by the agent from simulated PX4 and ArduPilot autopilots over
real UDP, reported per autopilot and judged against ``spec.firmware``."""

from __future__ import annotations

import pytest

from roost_api.autopilot import FirmwareRequirement
from roost_sim import FaultKind
from tests.support.hubclient import HubVehicle, hub_vehicle
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow


def firmware_condition(v: HubVehicle) -> tuple[str, str, str] | None:
    for c in v.agent.status().conditions:
        if c.type == "FirmwareAcceptable":
            return c.status, c.reason, c.message
    return None


def version_of(v: HubVehicle, name: str) -> str | None:
    for h in v.agent.status().autopilots:
        if h.name == name and h.firmware is not None:
            return h.firmware.version
    return None


def test_each_autopilots_firmware_is_reported_and_the_requirement_names_who_breaks_it() -> None:
    with hub_vehicle(["px4", "ardupilot", "px4"]) as v:
        wait_until(
            "firmware of all three",
            lambda: all(h.firmware is not None for h in v.agent.status().autopilots),
            10,
        )
        v.sim("fc3").firmware_version = (1, 14, 3)  # flashed: it says so after a reboot
        v.sim("fc3").inject(FaultKind.REBOOT)
        wait_until("fc3 read again", lambda: version_of(v, "fc3") == "1.14.3", 15)
        by_name = {h.name: h.firmware for h in v.agent.status().autopilots}
        fc1, fc2, fc3 = by_name["fc1"], by_name["fc2"], by_name["fc3"]
        assert fc1 is not None and fc2 is not None and fc3 is not None
        assert (fc1.version, fc1.version_type, fc1.git_hash) == (
            "1.16.0",
            "official",
            "d4a3b3c2e1f00abc",
        )
        assert "PARAM_ENCODE_BYTEWISE" in fc1.capabilities
        assert (fc2.version, fc2.git_hash) == ("4.7.0", "90700977")
        assert "PARAM_ENCODE_C_CAST" in fc2.capabilities
        assert fc3.version == "1.14.3"
        assert firmware_condition(v) is None  # nothing required, nothing judged
        v.agent.apply_spec(v.spec_with(firmware=FirmwareRequirement(px4_minimum="1.15.0")))
        wait_until("judged", lambda: firmware_condition(v) is not None, 5)
        status, reason, message = firmware_condition(v)  # type: ignore[misc]
        assert (status, reason) == ("False", "FirmwareBelowMinimum")
        assert message == "fc3 runs px4 1.14.3, below the required 1.15.0"
        v.agent.apply_spec(
            v.spec_with(
                firmware=FirmwareRequirement(px4_minimum="1.14.0", ardupilot_minimum="4.5.0")
            )
        )
        wait_until("acceptable", lambda: (firmware_condition(v) or ("",))[0] == "True", 5)
        v.agent.apply_spec(v.spec_with(firmware=FirmwareRequirement(identical=True)))
        wait_until(
            "differ", lambda: (firmware_condition(v) or ("", ""))[1] == "FirmwareVersionsDiffer", 5
        )
        assert "fc1 1.16.0 (d4a3b3c2e1f00abc), fc3 1.14.3" in firmware_condition(v)[2]  # type: ignore[index]
