"""Bridge drivers, the durable state file, restore rules and the CLI's config parsing."""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from roost_agent import links
from roost_agent.agent import restore_state
from roost_agent.bridge import BridgeError, GpioBridge, SimulatedBridge
from roost_agent.health import HealthTracker
from roost_agent.links import AckMailbox, AutopilotLink, UdpListen, UdpOut, open_transport
from roost_agent.main import load_spec, parse_autopilot
from roost_agent.state import PersistedState, StateFile
from roost_api.autopilot import CommandResult, RedundantAutopilotSpec, Thresholds
from roost_api.meta import Stack
from roost_mavlink import AGENT_COMPONENT_ID
from roost_sim import free_udp_port
from tests.support.kernelstamps import until_the_kernel_stamps_arrivals
from tests.support.waiting import wait_until

SPEC = RedundantAutopilotSpec.model_validate(
    {
        "vehicleName": "v1",
        "primary": "fc1",
        "autopilots": [
            {
                "name": f"fc{i}",
                "stack": "px4",
                "connection": f"udp://127.0.0.1:{14540 + i}",
                "sysid": i,
                "bridgeChannel": i - 1,
            }
            for i in (1, 2, 3)
        ],
    }
)
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


def test_udp_listener_replies_only_to_the_locked_autopilot_address() -> None:
    port = free_udp_port()
    listener = open_transport(f"udp://127.0.0.1:{port}")
    assert isinstance(listener, UdpListen)
    autopilot, spoofer = UdpOut("127.0.0.1", port), UdpOut("127.0.0.1", port)
    try:
        spoofer.send(b"spoof")
        autopilot.send(b"real")
        senders: list[tuple[bytes, object]] = []

        def both_arrived() -> bool:
            data, sender = listener.receive()
            if data:
                senders.append((data, sender))
            return len(senders) == 2

        wait_until("both datagrams", both_arrived, 5.0, 0.01)
        real = next(s for d, s in senders if d == b"real")
        listener.send(b"dropped: no locked peer yet")
        assert real is not None
        listener.lock_to(real)
        listener.send(b"reply")
        assert wait_until("the reply", lambda: autopilot.receive()[0], 5.0, 0.01) == b"reply"
        assert spoofer.receive()[0] == b""
    finally:
        for t in (listener, autopilot, spoofer):
            t.close()


def test_standalone_agent_imports_neither_kopf_nor_heavy_clients() -> None:
    """The agent must not import kopf; standalone it also skips the Kubernetes client and
    numpy (pulled in by pymavlink's mavutil), which would cost tens of MB on a vehicle."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent; "
        "print(sorted(m for m in ('kopf', 'kubernetes', 'numpy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_agent_never_imports_pymavlink() -> None:
    """Its MAVLink is roost_mavlink.codec: pymavlink's generated dialect alone costs ~7 MB
    of memory on a companion computer."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent, roost_agent.hub; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'pymavlink'))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_agent_in_cluster_mode_never_imports_the_kubernetes_package_nor_pydantic() -> None:
    """Its API client goes through roost_kube's minimal transport (about 13 MB less), and
    it reads and writes its RedundantAutopilot through roost_api.plain (about 15 MB less)."""
    probe = (
        "import sys, pathlib, roost_agent.main, roost_agent.publisher; "
        "from roost_agent.kube import AgentKube; "
        "AgentKube.from_environment(pathlib.Path(sys.argv[1])); "
        "print('kubernetes' in sys.modules, 'pydantic' in sys.modules)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "kubeconfig"
        config.write_text(
            "current-context: x\n"
            "contexts: [{name: x, context: {cluster: x, user: x}}]\n"
            "clusters: [{name: x, cluster: {server: 'https://127.0.0.1:1'}}]\n"
            "users: [{name: x, user: {token: t}}]\n"
        )
        out = subprocess.run(
            [sys.executable, "-c", probe, str(config)], capture_output=True, text=True, check=True
        )
    assert out.stdout.strip() == "False False"


def test_tcp_link_reads_only_its_autopilot_answers_as_191_and_reconnects() -> None:
    """A real TCP MAVLink peer (ArduPilot SITL serves TCP): frames from the autopilot
    count, a foreign sysid does not, the agent's own heartbeat goes out as component 191,
    and a closed connection is reopened."""
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    spec = SPEC.autopilots[0].model_copy(update={"connection": f"tcp://127.0.0.1:{port}"})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    try:
        conn, _ = server.accept()
        autopilot = common.MAVLink(None, srcSystem=1, srcComponent=1)
        foreign = common.MAVLink(None, srcSystem=99, srcComponent=1)
        for mav in (autopilot, foreign):
            conn.sendall(mav.heartbeat_encode(2, 12, 129, 0x03040000, 4).pack(mav))
        wait_until(
            "one accepted frame and one from another system",
            lambda: link.counters.accepted >= 1 and link.counters.other >= 1,
            5.0,
            0.01,
        )
        assert link.heartbeat() is not None and link.heartbeat()[0] == 0x03040000  # type: ignore[index]
        assert link.send_heartbeat()
        parser = common.MAVLink(None)
        conn.settimeout(5)
        msgs = parser.parse_buffer(conn.recv(1024)) or []
        assert [(m.get_type(), m.get_srcSystem(), m.get_srcComponent()) for m in msgs] == [
            ("HEARTBEAT", 1, AGENT_COMPONENT_ID)
        ]
        conn.close()
        again, _ = server.accept()  # the link noticed and connected again
        again.close()
        assert link.counters.reopened >= 1
    finally:
        link.stop()
        server.close()


def _px4_frames() -> tuple[bytes, bytes, bytes]:
    """(HEARTBEAT, CURRENT_MODE, a well-framed message of an id nobody defines) from
    system 1 component 1, as pymavlink's ``all`` dialect (which defines CURRENT_MODE)
    encodes them."""
    from pymavlink.dialects.v20 import all as everything  # noqa: PLC0415

    autopilot = everything.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = autopilot.heartbeat_encode(2, 12, 129, 0x03040000, 4).pack(autopilot)
    mode = autopilot.current_mode_encode(0, 0x03040000, 0x03040000).pack(autopilot)
    undefined = bytearray(beat)
    undefined[7:10] = (0xFFFF00).to_bytes(3, "little")
    return bytes(beat), bytes(mode), bytes(undefined)


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_a_message_the_pymavlink_dialect_lacks_is_counted_as_the_autopilots(
    transport: str,
) -> None:
    """PX4 v1.16's CURRENT_MODE (which pymavlink's dialect lacks) is accepted like any
    message of the autopilot, in UDP datagrams and in a TCP stream; a frame of an id
    nobody defines is counted ``unknown`` and costs nothing after it."""
    beat, mode, undefined = _px4_frames()
    peer = socket.socket(
        socket.AF_INET, socket.SOCK_DGRAM if transport == "udp" else socket.SOCK_STREAM
    )
    peer.bind(("127.0.0.1", 0))
    if transport == "udp":
        port = free_udp_port()
        connection = f"udp://127.0.0.1:{port}@127.0.0.1:{peer.getsockname()[1]}"
    else:
        peer.listen()
        connection = f"tcp://127.0.0.1:{peer.getsockname()[1]}"
    spec = SPEC.autopilots[0].model_copy(update={"connection": connection})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    try:
        if transport == "udp":  # bound (and locked to the peer) once the link opened
            wait_until("the link open", lambda: link.locked_address is not None, 5.0, 0.01)
            for datagram in (beat, mode, undefined, mode + beat):
                peer.sendto(datagram, ("127.0.0.1", port))
        else:
            conn, _ = peer.accept()
            conn.sendall(beat + mode + undefined + mode + beat)
        wait_until(
            "five frames read",
            lambda: link.counters.accepted + link.counters.unknown >= 5,
            5.0,
            0.01,
        )
        c = link.counters
        assert (c.accepted, c.unknown, c.bad, c.errors) == (4, 1, 0, 0)
        assert link.tracker.stream_facts().counts["CURRENT_MODE"] == 2
    finally:
        link.stop()
        peer.close()


def test_tcp_listener_link_reads_the_autopilot_that_connects_to_it() -> None:
    """``tcpin://``: the link listens, an autopilot connects; the reader follows the
    accepted connection (its descriptor is not the listening one) and reads its frames,
    also after the autopilot reconnects."""
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    spec = SPEC.autopilots[0].model_copy(update={"connection": f"tcpin://127.0.0.1:{port}"})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    autopilot = common.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        for connection in (1, 2):
            client = wait_until(
                "the link listening",
                lambda: _connected(port),
                5.0,
                0.02,
            )
            with client:
                before = link.counters.accepted
                for _ in range(3):
                    client.sendall(autopilot.heartbeat_encode(2, 12, 129, 0, 4).pack(autopilot))
                wait_until(
                    f"frames of connection {connection}",
                    lambda before=before: link.counters.accepted >= before + 3,  # type: ignore[misc]
                    5.0,
                    0.01,
                )
    finally:
        link.stop()


def _connected(port: int) -> socket.socket | None:
    try:
        return socket.create_connection(("127.0.0.1", port), timeout=1.0)
    except OSError:
        return None


@pytest.mark.parametrize("later_than_slack", [False, True])
def test_a_datagram_read_late_keeps_its_kernel_arrival_time(
    monkeypatch: pytest.MonkeyPatch, later_than_slack: bool
) -> None:
    """The reader reads once per tick; the health tracker must see when a message arrived
    (the kernel's receive timestamp), not when it was read. Read 50 ms late with the
    slack widened (a loaded machine may oversleep the 50 ms): its arrival. Read 300 ms
    late, beyond the slack: the slack before the read, never the read time (which would
    delay a silence by the whole wait)."""
    if not later_than_slack:
        monkeypatch.setattr(links, "STAMP_SLACK_S", 10.0)
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    autopilot_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot_socket.bind(("127.0.0.1", 0))
    sender = autopilot_socket.getsockname()
    port = free_udp_port()
    spec = SPEC.autopilots[0].model_copy(
        update={"connection": f"udp://127.0.0.1:{port}@{sender[0]}:{sender[1]}"}
    )
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    session = link._open()
    try:
        until_the_kernel_stamps_arrivals()
        mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
        sent_at = time.monotonic()
        autopilot_socket.sendto(
            mav.heartbeat_encode(2, 12, 129, 0, 4).pack(mav), ("127.0.0.1", port)
        )
        # Loopback usually delivers inside sendto, but the kernel may defer it (to
        # ksoftirqd); the stamp is taken on delivery, so wait for the socket to hold it.
        # (A heartbeat goes to the link's urgent socket where the kernel steers.)
        urgent = session.transport.urgent_fileno()
        descriptors = [session.transport.fileno(), *([] if urgent is None else [urgent])]
        assert select.select(descriptors, [], [], 5.0)[0]
        delivered = time.monotonic()
        time.sleep(0.3 if later_than_slack else 0.05)
        read_from = time.monotonic()
        link._drain(session)
        read_until = time.monotonic()
        beat = link.heartbeat()
        assert beat is not None
        if later_than_slack:
            slack = links.STAMP_SLACK_S
            assert read_from - slack - 0.001 <= beat[2] <= read_until - slack + 0.001
        else:  # arrival (within the clock conversion's rounding), not the read 50 ms later
            assert sent_at - 0.001 <= beat[2] <= delivered + 0.001
    finally:
        link._close()
        autopilot_socket.close()


def test_the_realtime_offset_matches_the_clocks() -> None:
    """Turning a kernel stamp (realtime) into the agent's clock (monotonic)."""
    offset = links.realtime_offset()
    assert abs((time.time() - time.monotonic()) - offset) < 0.05
