"""Declared autopilot parameters, kept by the agent on simulated autopilots over real UDP.

The simulated autopilots speak the MAVLink parameter protocol with each firmware's names,
types and integer encoding (roost_sim.params); the agent writes the declared values,
confirms them by the echoed PARAM_VALUE, keeps reading them back and reports each
autopilot's ``ParametersInSync`` condition. A ground-station client on the agent's hub
(tests.support.hubclient) plays "another client"; the simulated bridge is the only
stand-in (no GPIO hardware here).
"""

from __future__ import annotations

import math
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_api.autopilot import DriftPolicy, ParametersSpec, ParameterValue
from roost_mavlink import MavResult
from tests.support.hubclient import VEHICLE_SYSID, HubVehicle, hub_vehicle
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

POLL_S = 0.05
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_NAV_LAND = 21
KIND = "ParametersInSync"


def declared(px4: dict[str, float], ardupilot: dict[str, float], **kw: object) -> ParametersSpec:
    return ParametersSpec(
        px4=[ParameterValue(name=n, value=v) for n, v in px4.items()],
        ardupilot=[ParameterValue(name=n, value=v) for n, v in ardupilot.items()],
        **kw,  # type: ignore[arg-type]
    )


def reason_is(v: HubVehicle, name: str, reason: str) -> bool:
    cond = v.condition(name, KIND)
    return cond is not None and cond.reason == reason


def test_declared_parameters_reach_every_autopilot_of_each_stack_with_its_types() -> None:
    params = declared(
        # PX4: a FLOAT, an INT32 (sent bytewise), RC calibration
        {"MIS_TAKEOFF_ALT": 6.2, "GF_ACTION": 3, "RC1_REV": -1},
        # ArduPilot: AP_Float (cm), AP_Int8, AP_Int16 (sent as numbers)
        {"PILOT_TKOFF_ALT": 620, "DISARM_DELAY": 5, "RC1_MIN": 1000},
    )
    with hub_vehicle(["px4", "ardupilot", "px4"], parameters=params) as v:
        for sim in v.sims:
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 15)
        for name in ("fc1", "fc3"):
            store = v.sim(name).params
            assert store.get("MIS_TAKEOFF_ALT") == pytest.approx(6.2)
            assert (store.get("GF_ACTION"), store.get("RC1_REV")) == (3, -1)
        ardu = v.sim("fc2").params
        assert ardu.get("PILOT_TKOFF_ALT") == pytest.approx(620)
        assert (ardu.get("DISARM_DELAY"), ardu.get("RC1_MIN")) == (5, 1000)
        assert v.sim("fc2").config.takeoff_alt_m == pytest.approx(6.2)  # it acts on it
        cond = v.condition("fc1", KIND)
        assert cond is not None and cond.status == "True"


def test_the_keepers_rest_between_heartbeats_and_a_declaration_wakes_them() -> None:
    """With nothing to ask (the streams arrive as requested, the firmware is known,
    nothing declared) the keepers are stepped with the 1 Hz heartbeat, not every
    STREAM_CHECK_S; a spec that declares parameters starts the conversation at once, and
    it is carried to its end."""
    with hub_vehicle(["px4", "ardupilot"]) as v:
        agent = v.agent

        def at_rest() -> bool:
            before = agent.keeper_rounds
            time.sleep(2.0)  # not a wait for a condition: the window rounds are counted in
            return agent.keeper_rounds - before <= 3  # 1 Hz: 2 or 3; every 0.25 s: 8

        wait_until("the keepers at rest", at_rest, 30, POLL_S)
        params = declared({"GF_ACTION": 3}, {"DISARM_DELAY": 5})
        agent.apply_spec(v.spec_with(parameters=params))
        for sim in v.sims:
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 15)
        assert v.sim("fc1").params.get("GF_ACTION") == 3
        assert v.sim("fc2").params.get("DISARM_DELAY") == 5


def test_a_change_by_another_client_is_drift_naming_both_values() -> None:
    params = declared({"GF_ACTION": 3, "MIS_TAKEOFF_ALT": 4.0}, {})
    with hub_vehicle(["px4", "px4"], parameters=params) as v:
        for sim in v.sims:
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 15)
        v.sim("fc2").params.set("GF_ACTION", 1)  # another link of fc2: no echo to the agent
        wait_until("fc2 drifted", lambda: reason_is(v, "fc2", "Drifted"), 10, POLL_S)
        cond = v.condition("fc2", KIND)
        assert cond is not None and cond.status == "False"
        assert "GF_ACTION is 1, declared 3" in cond.message
        assert reason_is(v, "fc1", "InSync")
        assert v.sim("fc2").params.get("GF_ACTION") == 1  # policy Report: not put back


def test_a_write_through_the_hub_reaches_the_standby_and_restore_puts_it_back() -> None:
    params = declared({"MIS_TAKEOFF_ALT": 4.0}, {}, on_drift=DriftPolicy.RESTORE)
    with hub_vehicle(["px4", "px4"], parameters=params) as v:
        for sim in v.sims:
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 15)
        drifts: list[str] = []
        v.agent.subscribe(
            lambda e: drifts.append(e.message) if e.reason == "ParameterDrifted" else None
        )
        v.client.mav.param_set_send(
            VEHICLE_SYSID, 1, b"MIS_TAKEOFF_ALT", 6.2, mavlink.MAV_PARAM_TYPE_REAL32
        )
        wait_until("both drifted", lambda: len({m.split(":")[0] for m in drifts}) == 2, 10, POLL_S)
        for sim in v.sims:  # and both written back
            wait_until(
                f"{sim.name} restored",
                lambda s=sim: s.params.get("MIS_TAKEOFF_ALT") == pytest.approx(4.0),
                10,
                POLL_S,
            )
        assert all("MIS_TAKEOFF_ALT is 6.2, declared 4; writing it back" in m for m in drifts)


def test_without_declared_parameters_a_clients_write_keeps_the_standby_in_step() -> None:
    with hub_vehicle(["px4", "px4", "ardupilot"]) as v:
        v.client.mav.param_set_send(
            VEHICLE_SYSID, 1, b"MIS_TAKEOFF_ALT", 6.2, mavlink.MAV_PARAM_TYPE_REAL32
        )
        echo = v.client.wait_for(lambda r: r.kind == "PARAM_VALUE", 5)
        assert echo.msg.param_id == "MIS_TAKEOFF_ALT" and echo.sysid == VEHICLE_SYSID
        for name in ("fc1", "fc2"):
            wait_until(
                f"{name} took it",
                lambda n=name: v.sim(n).config.takeoff_alt_m == pytest.approx(6.2),
                5,
                POLL_S,
            )
        assert v.sim("fc3").config.takeoff_alt_m != pytest.approx(6.2)  # another stack
        reported = [c.type for h in v.agent.status().autopilots for c in h.conditions]
        assert KIND not in reported  # nothing declared, nothing reported


def test_writes_wait_while_armed_and_happen_after_landing() -> None:
    with hub_vehicle(["px4", "px4"], parameters=declared({"GF_ACTION": 3}, {})) as v:
        for sim in v.sims:
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 15)
        assert (
            v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
        )
        takeoff = (0, 0, 0, math.nan, 0, 0, math.nan)
        assert v.client.command(VEHICLE_SYSID, MAV_CMD_NAV_TAKEOFF, *takeoff) == MavResult.ACCEPTED
        for sim in v.sims:
            sim.wait_until(lambda s: s.landed_state == "InAir", timeout=15)
        # a new declared value while flying
        assert v.agent.apply_spec(v.spec_with(parameters=declared({"GF_ACTION": 4}, {}))) is None
        for sim in v.sims:
            wait_until(
                f"{sim.name} deferred", lambda s=sim: reason_is(v, s.name, "DeferredWhileArmed"), 10
            )
            assert sim.params.get("GF_ACTION") == 3
        assert v.client.command(VEHICLE_SYSID, MAV_CMD_NAV_LAND) == MavResult.ACCEPTED
        for sim in v.sims:
            sim.wait_until(lambda s: not s.armed, timeout=30)
        for sim in v.sims:
            wait_until(f"{sim.name} written", lambda s=sim: s.params.get("GF_ACTION") == 4, 10)
            wait_until(f"{sim.name} in sync", lambda s=sim: reason_is(v, s.name, "InSync"), 10)


def test_unknown_names_and_values_the_type_cannot_hold_are_reported_not_written() -> None:
    params = declared({"NO_SUCH_PARAM": 1, "GF_ACTION": 2.5}, {})
    with hub_vehicle(["px4", "px4"], parameters=params) as v:
        wait_until("fc1 reported", lambda: reason_is(v, "fc1", "UnknownParameter"), 15)
        cond = v.condition("fc1", KIND)
        assert cond is not None and "NO_SUCH_PARAM" in cond.message
        assert v.sim("fc1").params.get("GF_ACTION") == 2  # PX4's default: 2.5 never written
        v.agent.apply_spec(v.spec_with(parameters=declared({"GF_ACTION": 2.5}, {})))
        wait_until("fc1 invalid", lambda: reason_is(v, "fc1", "InvalidValue"), 10)
        cond = v.condition("fc1", KIND)
        assert cond is not None and "2.5 is not a whole number (INT32 parameter)" in cond.message
