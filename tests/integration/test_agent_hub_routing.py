"""What the MAVLink hub hands to which autopilot link: client messages, mirrors to
standbys, awaited mirrored commands, the route after a switch.

A real hub (its UDP endpoint bound on 127.0.0.1) with recording links in place of
autopilot links, because what is checked is which frames the hub hands to which link.
The hub's pure parts are in ``tests/unit/test_agent_hub_rules.py``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.hub import (
    Hub,
)
from roost_api.autopilot import (
    AutopilotSpec,
    HubSpec,
    RedundantAutopilotSpec,
)
from tests.support.mavframes import VEHICLE, client_msg, encode, heartbeat, parse

# -- frames ------------------------------------------------------------------------------


class RecordingLink:
    """Stands in for an autopilot link: records the frames the hub hands it."""

    def __init__(self, spec: AutopilotSpec) -> None:
        self.name = spec.name
        self.spec = spec
        self.tap: Any = None
        self.log_sink: Any = None
        self.routed = False
        self.frames: list[Any] = []
        self.commands: list[tuple[int, tuple[float, ...]]] = []

    def send_frame(self, frame: bytes) -> bool:
        self.frames.append(parse(frame))
        return True

    def send_command(self, command: int, params: tuple[float, ...]) -> bool:
        self.commands.append((command, params))
        return True

    def fast_source(self) -> None:
        return None  # no socket: the hub routes in Python


def hub_spec(
    stacks: tuple[str, ...] = ("px4", "px4", "px4"), mirror: bool = True
) -> RedundantAutopilotSpec:
    return RedundantAutopilotSpec(
        vehicle_name="v1",
        autopilots=[
            AutopilotSpec(
                name=f"fc{i + 1}",
                stack=stack,
                connection=f"udp://127.0.0.1:{14601 + i}",
                sysid=i + 1,
                bridge_channel=i,
            )
            for i, stack in enumerate(stacks)
        ],
        primary="fc1",
        hub=HubSpec(sysid=VEHICLE, udp="127.0.0.1:0", mirror=mirror),
    )


@pytest.fixture
def routed() -> Iterator[tuple[Hub, dict[str, RecordingLink]]]:
    spec = hub_spec(("px4", "px4", "ardupilot"))
    hub = Hub(spec, "fc1")
    links = {a.name: RecordingLink(a) for a in spec.autopilots}
    for link in links.values():
        hub.attach(link)
    yield hub, links
    hub.close()


def kinds(link: RecordingLink) -> list[str]:
    return [m.get_type() for m in link.frames]


def test_client_messages_go_to_the_active_and_flight_state_to_every_standby(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    hub.route(
        client_msg(mavlink.MAVLink_command_long_message(VEHICLE, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    )
    hub.route(
        client_msg(mavlink.MAVLink_command_long_message(VEHICLE, 1, 512, 0, 33, 0, 0, 0, 0, 0, 0))
    )
    hub.route(client_msg(mavlink.MAVLink_param_request_list_message(VEHICLE, 1)))
    setpoint = mavlink.MAVLink_set_position_target_local_ned_message(
        0, VEHICLE, 1, 1, 0xFF8, 1, 2, -5, 0, 0, 0, 0, 0, 0, 0, 0
    )
    hub.route(client_msg(setpoint))
    assert kinds(links["fc1"]) == [
        "COMMAND_LONG",
        "COMMAND_LONG",
        "PARAM_REQUEST_LIST",
        "SET_POSITION_TARGET_LOCAL_NED",
    ]
    for name, sysid in (("fc2", 2), ("fc3", 3)):  # arm and setpoint only, each readdressed
        assert kinds(links[name]) == ["COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED"]
        assert [m.target_system for m in links[name].frames] == [sysid, sysid]
    assert [m.target_system for m in links["fc1"].frames] == [1, 1, 1, 1]
    assert hub.snapshot("fc2").awaiting.keys() == {400}  # type: ignore[union-attr]


def test_mode_changes_are_mirrored_only_within_a_stack(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    hub.route(
        client_msg(mavlink.MAVLink_command_long_message(VEHICLE, 1, 176, 0, 1, 4, 3, 0, 0, 0, 0))
    )
    hub.route(client_msg(mavlink.MAVLink_set_mode_message(VEHICLE, 1, 4)))
    assert kinds(links["fc2"]) == ["COMMAND_LONG", "SET_MODE"]
    assert kinds(links["fc3"]) == []  # ArduPilot: the PX4 mode number means something else


def test_parameter_writes_are_mirrored_within_a_stack_and_reads_are_not(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    real32 = mavlink.MAV_PARAM_TYPE_REAL32
    hub.route(
        client_msg(mavlink.MAVLink_param_set_message(VEHICLE, 1, b"MIS_TAKEOFF_ALT", 6.2, real32))
    )
    hub.route(
        client_msg(mavlink.MAVLink_param_request_read_message(VEHICLE, 1, b"MIS_TAKEOFF_ALT", -1))
    )
    assert kinds(links["fc1"]) == ["PARAM_SET", "PARAM_REQUEST_READ"]
    [mirrored] = links["fc2"].frames  # the PX4 standby, readdressed
    assert (mirrored.get_type(), mirrored.target_system) == ("PARAM_SET", 2)
    assert (mirrored.param_id, mirrored.param_value) == ("MIS_TAKEOFF_ALT", pytest.approx(6.2))
    assert kinds(links["fc3"]) == []  # ArduPilot has no MIS_TAKEOFF_ALT (PILOT_TKOFF_ALT, cm)


def test_after_set_active_the_route_follows_and_mirrors_go_to_the_old_active(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    hub.set_active("fc2")
    hub.route(client_msg(mavlink.MAVLink_param_request_list_message(VEHICLE, 1)))
    hub.route(client_msg(heartbeat()))
    assert kinds(links["fc2"]) == ["PARAM_REQUEST_LIST", "HEARTBEAT"]
    assert kinds(links["fc1"]) == ["HEARTBEAT"]  # a GCS heartbeat reaches every standby
    assert hub.counters.switches == 1


def test_without_mirroring_standbys_get_nothing() -> None:
    spec = hub_spec(mirror=False)
    hub = Hub(spec, "fc1")
    links = {a.name: RecordingLink(a) for a in spec.autopilots}
    try:
        for link in links.values():
            hub.attach(link)
        hub.route(
            client_msg(
                mavlink.MAVLink_command_long_message(VEHICLE, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
            )
        )
        assert kinds(links["fc1"]) == ["COMMAND_LONG"]
        assert kinds(links["fc2"]) == kinds(links["fc3"]) == []
    finally:
        hub.close()


def test_standby_answers_are_recorded_never_forwarded(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    hub.route(
        client_msg(mavlink.MAVLink_command_long_message(VEHICLE, 1, 176, 0, 1, 4, 3, 0, 0, 0, 0))
    )
    ack = parse(encode(mavlink.MAVLink_command_ack_message(176, 2, 0, 0, 255, 190), sysid=2))
    links["fc2"].tap(ack, 10.0)
    seen = hub.snapshot("fc2")
    assert seen is not None and 176 in seen.rejected and not seen.awaiting
    assert hub.counters.to_clients == 0 and hub.counters.dropped_standby == 1
    accepted = parse(encode(mavlink.MAVLink_command_ack_message(176, 0, 0, 0, 255, 190), sysid=2))
    links["fc2"].tap(accepted, 11.0)
    assert not seen.rejected  # a later acceptance resolves it


class PromptLink(RecordingLink):
    """A standby that answers a mirrored command before ``send_frame`` returns: the link
    reader's thread can read the answer while the hub's thread is still sending."""

    def send_frame(self, frame: bytes) -> bool:
        sent = super().send_frame(frame)
        msg = self.frames[-1]
        if msg.get_type() == "COMMAND_LONG":
            ack = mavlink.MAVLink_command_ack_message(msg.command, 0, 0, 0, 255, 190)
            self.tap(parse(encode(ack, sysid=self.spec.sysid)), 10.0)
        return sent


class RefusingLink(RecordingLink):
    """A standby whose link cannot send (down, reopening)."""

    def send_frame(self, frame: bytes) -> bool:
        return False


@pytest.mark.parametrize(
    ("link", "awaited"), [(PromptLink, set()), (RefusingLink, set()), (RecordingLink, {400})]
)
def test_a_mirrored_command_is_awaited_until_its_answer_whenever_that_comes(
    link: type[RecordingLink], awaited: set[int]
) -> None:
    spec = hub_spec(("px4", "px4"))
    hub = Hub(spec, "fc1")
    try:
        for autopilot in spec.autopilots:
            hub.attach((link if autopilot.name == "fc2" else RecordingLink)(autopilot))
        arm = mavlink.MAVLink_command_long_message(VEHICLE, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        hub.route(client_msg(arm))
        seen = hub.snapshot("fc2")
        assert seen is not None and set(seen.awaiting) == awaited
    finally:
        hub.close()


def test_ardupilot_standbys_get_the_standby_aux_function(
    routed: tuple[Hub, dict[str, RecordingLink]],
) -> None:
    hub, links = routed
    hub.aux_standby("fc1")
    assert links["fc3"].commands == [(218, (76.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0))]
    assert links["fc1"].commands == links["fc2"].commands == []  # PX4 has no such function
    hub.aux_standby("fc3")
    assert links["fc3"].commands[-1] == (218, (76.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
