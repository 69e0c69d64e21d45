"""Bridge drivers, the durable state file, restore rules and the CLI's config parsing."""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from roost_agent import links
from roost_agent.agent import restore_state
from roost_agent.bridge import BridgeError, GpioBridge, SimulatedBridge
from roost_agent.links import AckMailbox
from roost_agent.main import load_spec, parse_autopilot
from roost_agent.state import PersistedState, StateFile
from roost_api.autopilot import CommandResult
from tests.support.agentspec import SPEC

NOW = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)


def saved(active: str = "fc2", **fields: object) -> PersistedState:
    return PersistedState.from_api(
        {"spec": SPEC.to_api(), "active": active, "savedAt": NOW, **fields}
    )


# -- bridge ------------------------------------------------------------------------------


def test_simulated_bridge_records_selections_and_tells_listeners() -> None:
    bridge = SimulatedBridge([0, 1], initial=0)
    heard: list[int] = []
    bridge.add_listener(heard.append)
    bridge.select(1)
    assert bridge.selected == 1 and [s.channel for s in bridge.history] == [0, 1]
    assert heard == [0, 1]  # the current channel first, then every switch
    assert bridge.history[0].at <= bridge.history[1].at
    with pytest.raises(BridgeError):
        bridge.select(7)
    assert bridge.selected == 1


def test_gpio_bridge_reports_a_missing_chip_clearly(tmp_path: Path) -> None:
    with pytest.raises(BridgeError, match="cannot request GPIO lines"):
        GpioBridge(str(tmp_path / "gpiochip9"), [0, 1], 0)
    with pytest.raises(BridgeError, match="initial channel"):
        GpioBridge(str(tmp_path / "gpiochip9"), [0, 1], 5)


GPIO_SIM = Path("/sys/kernel/config/gpio-sim")


@contextlib.contextmanager
def gpio_sim_chip(lines: int) -> Iterator[tuple[str, Path]]:
    """A simulated GPIO chip from the kernel's gpio-sim module (configfs)."""
    device = GPIO_SIM / f"roost-test-{os.getpid()}"
    bank = device / "bank0"
    bank.mkdir(parents=True)
    try:
        (bank / "num_lines").write_text(str(lines))
        (device / "live").write_text("1")
        chip = (bank / "chip_name").read_text().strip()
        dev_name = (device / "dev_name").read_text().strip()
        yield f"/dev/{chip}", Path(f"/sys/devices/platform/{dev_name}/{chip}")
    finally:
        (device / "live").write_text("0")
        bank.rmdir()
        device.rmdir()


@pytest.mark.skipif(
    not GPIO_SIM.is_dir() or os.geteuid() != 0,
    reason="needs the kernel's gpio-sim module (configfs /sys/kernel/config/gpio-sim) and "
    "root; this machine's kernel has no GPIO character devices at all, so the GPIO driver "
    "is exercised here only up to requesting the lines",
)
def test_gpio_bridge_drives_one_hot_lines_on_a_simulated_chip() -> None:
    with gpio_sim_chip(4) as (chip, sysfs):

        def levels() -> list[int]:
            return [int((sysfs / f"sim_gpio{i}" / "value").read_text()) for i in range(3)]

        bridge = GpioBridge(chip, [0, 1, 2], 1)
        try:
            assert levels() == [0, 1, 0]  # the initial channel is asserted at request time
            bridge.select(2)
            assert levels() == [0, 0, 1] and bridge.selected == 2
        finally:
            bridge.close()
        low = GpioBridge(chip, [0, 1, 2], 0, active_low=True)
        try:
            assert levels() == [0, 1, 1]
        finally:
            low.close()


# -- durable state -----------------------------------------------------------------------


def test_state_file_round_trip_is_atomic(tmp_path: Path) -> None:
    store = StateFile(tmp_path / "agent-state.json")
    assert store.load() is None
    result = CommandResult(id="c1", result="Executed", message="ok", time=NOW)
    state = saved(latched=True, failedFrom=["fc1"], failoverCount=2, commands=[result.to_api()])
    store.save(state)
    assert store.load() == state
    assert [p.name for p in tmp_path.iterdir()] == ["agent-state.json"]  # no temp file left
    doc = json.loads((tmp_path / "agent-state.json").read_text())
    assert doc["active"] == "fc2" and doc["failedFrom"] == ["fc1"]


def test_corrupt_state_file_is_moved_aside_not_trusted(tmp_path: Path) -> None:
    path = tmp_path / "agent-state.json"
    path.write_text('{"active": "fc2", "spec": ')
    assert StateFile(path).load() is None
    assert (tmp_path / "agent-state.json.corrupt").exists() and not path.exists()


def test_restore_keeps_the_saved_active_autopilot_and_latch() -> None:
    state = restore_state(SPEC, saved(latched=True, failedFrom=["fc1", "gone"], failoverCount=1))
    assert (state.active, state.latched, state.failover_count) == ("fc2", True, 1)
    assert state.failed_from == {"fc1"}  # names no longer in the spec are dropped
    assert state.in_flight is None and state.failing_since is None  # rebuilt from telemetry


def test_restore_falls_back_to_the_primary() -> None:
    assert restore_state(SPEC, None).active == "fc1"
    assert restore_state(SPEC, saved(active="removed")).active == "fc1"


# -- CLI config --------------------------------------------------------------------------


def test_autopilot_flag() -> None:
    spec = parse_autopilot(
        "name=fc1,stack=ardupilot,connection=tcp://127.0.0.1:5760,sysid=3,channel=1"
    )
    assert (spec.name, spec.stack, spec.sysid, spec.bridge_channel) == ("fc1", "ardupilot", 3, 1)
    with pytest.raises(Exception, match="bad --autopilot"):
        parse_autopilot("name=fc1,stack=px5,connection=udp://:1,sysid=1,channel=0")


def test_config_file_takes_a_whole_object_or_a_bare_spec(tmp_path: Path) -> None:
    whole = tmp_path / "ra.yaml"
    whole.write_text(
        json.dumps(
            {"kind": "RedundantAutopilot", "metadata": {"generation": 4}, "spec": SPEC.to_api()}
        )
    )
    spec, generation = load_spec(whole)
    assert (spec.to_api(), generation) == (SPEC.to_api(), 4)
    bare = tmp_path / "spec.json"
    bare.write_text(json.dumps(SPEC.to_api()))
    spec, generation = load_spec(bare)
    assert (spec.to_api(), generation) == (SPEC.to_api(), None)


# -- link plumbing -----------------------------------------------------------------------


def test_ack_mailbox_returns_only_acks_newer_than_the_request() -> None:
    box = AckMailbox()
    box.put(176, 1)
    serial = box.serial(176)
    assert box.wait(176, serial, 0.01) is None  # the old ack does not answer a new request
    box.put(176, 0)
    assert box.wait(176, serial, 0.01) == 0


def test_the_realtime_offset_matches_the_clocks() -> None:
    """Turning a kernel stamp (realtime) into the agent's clock (monotonic)."""
    offset = links.realtime_offset()
    assert abs((time.time() - time.monotonic()) - offset) < 0.05
