"""Flight records with the real agent and simulated autopilots over real UDP.

One PX4 and one ArduPilot autopilot behind the agent's hub; a ground-station client on
the hub arms and disarms the vehicle. The recorder writes the flight, then fetches both
autopilots' own logs over the MAVLink log protocol; the tlog is read back with
pymavlink, the ArduPilot log with pymavlink's DataFlash reader, the ULog with the
fetcher's own structural check and a field-level decode here (no ULog reader is among
the project's dependencies). The simulated bridge is the only stand-in (no GPIO).
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from pymavlink import DFReader, mavutil

from roost_agent.records import MANIFEST, Manifest, flight_id, read_manifests, write_manifest
from roost_agent.records_logs import FetchSettings, LogFetcher, check_ulog
from roost_agent.records_recorder import FlightRecorder
from roost_api.records import FileState, FlightState
from roost_mavlink import MAV_CMD_COMPONENT_ARM_DISARM, MavResult
from tests.support.hubclient import VEHICLE_SYSID, HubVehicle, hub_vehicle
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

SAMPLES = 15  # 1.5 s at the simulated logs' 10 Hz


@pytest.fixture
def recorded(tmp_path: Path) -> Iterator[tuple[HubVehicle, FlightRecorder]]:
    with hub_vehicle(["px4", "ardupilot"]) as v:
        fetcher = LogFetcher(
            lambda: v.agent.links, settings=FetchSettings(rate_bytes_per_s=400_000)
        )
        recorder = FlightRecorder(
            v.agent, tmp_path / "records", budget_bytes=50_000_000, fetch_logs=fetcher
        )
        recorder.start()
        try:
            yield v, recorder
        finally:
            recorder.stop()


def fly_once(v: HubVehicle, during: Callable[[], None] = lambda: None) -> None:
    """Arm, stay armed a moment (calling ``during``), disarm (every autopilot follows
    the mirrored command)."""
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
    wait_until("both armed", lambda: all(s.snapshot().armed for s in v.sims), 5)
    during()
    wait_until(
        "a second of samples logged",
        lambda: all(s.logs.samples_logging >= SAMPLES for s in v.sims),
        10,
    )
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 0) == MavResult.ACCEPTED
    wait_until("both disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 5)


def settled(root: Path) -> Manifest:
    def done() -> bool:
        found = read_manifests(root)
        return bool(found) and found[0].state in (FlightState.COMPLETE, FlightState.FAILED)

    wait_until("the flight's record settled", done, 30)
    return read_manifests(root)[0]


def ulog_records(data: bytes) -> list[tuple[str, bytes]]:
    at, out = 16, []
    while at < len(data):
        size, kind = struct.unpack_from("<HB", data, at)
        out.append((chr(kind), data[at + 3 : at + 3 + size]))
        at += 3 + size
    return out


def test_a_flight_leaves_tlog_decisions_params_and_both_autopilots_logs(
    recorded: tuple[HubVehicle, FlightRecorder],
) -> None:
    v, recorder = recorded
    standby = v.sims[1]

    def gyro_fault_on_the_standby() -> None:
        standby.inject("sensor", "gyro")
        wait_until(
            "the standby judged",
            lambda: v.agent.assessments()[standby.name].level.value != "OK",
            5,
            0.02,
        )
        standby.clear("sensor")
        wait_until(
            "the standby healthy again",
            lambda: v.agent.assessments()[standby.name].level.value == "OK",
            5,
            0.02,
        )

    fly_once(v, gyro_fault_on_the_standby)
    manifest = settled(recorder.root)
    assert manifest.state is FlightState.COMPLETE, manifest
    assert manifest.flight_id.startswith("v1-")
    assert manifest.disarmed_at is not None and manifest.disarmed_at > manifest.armed_at
    assert manifest.dropped == {"tlog": 0, "decisions": 0}
    flight = recorder.root / manifest.flight_id
    files = {f.path: f for f in manifest.files}
    assert all(f.state is FileState.COMPLETE for f in files.values()), files

    # the tlog: pymavlink reads it back, both directions and both autopilots are in it
    tlog = mavutil.mavlink_connection(str(flight / "hub.tlog"))
    seen: dict[tuple[int, str], int] = {}
    arm_commands = []
    while (msg := tlog.recv_match()) is not None:
        key = (msg.get_srcSystem(), msg.get_type())
        seen[key] = seen.get(key, 0) + 1
        if msg.get_type() == "COMMAND_LONG" and msg.command == MAV_CMD_COMPONENT_ARM_DISARM:
            arm_commands.append((msg.target_system, msg.param1, getattr(msg, "_timestamp", 0)))
    sysids = {s.sysid for s in v.sims}
    for sysid in sysids:
        assert seen.get((sysid, "HEARTBEAT"), 0) >= 1
        assert seen.get((sysid, "COMMAND_ACK"), 0) >= 1  # the answers to the arm command
    # the client's arm (kept from before arming) and disarm went to both autopilots
    assert {(t, p) for t, p, _ in arm_commands} >= {(s, 1.0) for s in sysids} | {
        (s, 0.0) for s in sysids
    }
    assert all(at > 1.7e9 for _, _, at in arm_commands)  # wall-clock timestamps

    # decisions: the agent's events, JSON lines
    events = [json.loads(line) for line in (flight / "decisions.jsonl").read_text().splitlines()]
    fault = [
        e
        for e in events
        if e["event"] == "HealthChanged" and e["message"].startswith(f"{standby.name}: OK -> ")
    ]
    assert fault and fault[0]["health"]["reasons"]  # the transition with its evidence
    recovered = [e for e in events if e["event"] == "HealthChanged" and " -> OK" in e["message"]]
    assert any(e["autopilot"] == standby.name for e in recovered)

    # parameters at arming, per autopilot
    for sim in v.sims:
        doc = json.loads((flight / "params" / f"{sim.name}.json").read_text())
        assert doc["count"] == len(sim.params.names())
        assert doc["complete"] is True
        assert set(doc["params"]) == set(sim.params.names())

    # the autopilots' own logs: a ULog from PX4 and a DataFlash log from ArduPilot
    px4, ardupilot = v.sims
    ulg = files[f"autopilot-logs/{px4.name}/1.ulg"]
    data = (flight / ulg.path).read_bytes()
    assert ulg.bytes == len(data) == len(px4.logs.logs[0].data)
    assert check_ulog(data) is None
    positions = [b for k, b in ulog_records(data) if k == "D" and b[:2] == b"\0\0"]
    assert len(positions) >= SAMPLES
    bin_entry = files[f"autopilot-logs/{ardupilot.name}/1.bin"]
    assert (flight / bin_entry.path).read_bytes() == ardupilot.logs.logs[0].data
    reader: Any = DFReader.DFReader_binary(str(flight / bin_entry.path))
    kinds: dict[str, int] = {}
    while (m := reader.recv_msg()) is not None:
        kinds[m.get_type()] = kinds.get(m.get_type(), 0) + 1
    assert kinds["PARM"] == len(ardupilot.params.names())
    assert kinds["GPS"] >= SAMPLES
    assert kinds["BARO"] == kinds["GPS"]


@pytest.fixture
def slow_fetch(tmp_path: Path) -> Iterator[tuple[HubVehicle, FlightRecorder, LogFetcher]]:
    """A fetch slow enough (small windows, a low rate) to be cut in the middle."""
    with hub_vehicle(["px4", "px4"]) as v:
        settings = FetchSettings(rate_bytes_per_s=2500, window=450, request_timeout_s=0.5)
        fetcher = LogFetcher(lambda: v.agent.links, settings=settings)
        recorder = FlightRecorder(
            v.agent, tmp_path / "records", budget_bytes=50_000_000, fetch_logs=fetcher
        )
        recorder.start()
        try:
            yield v, recorder, fetcher
        finally:
            recorder.stop()


def test_a_download_cut_by_loss_a_drop_and_a_reboot_resumes_to_the_whole_file(
    slow_fetch: tuple[HubVehicle, FlightRecorder, LogFetcher],
) -> None:
    v, recorder, fetcher = slow_fetch
    sim = v.sims[0]  # fetched first
    fly_once(v)
    wait_until("the download started", lambda: fetcher.bytes_fetched > 0, 10, 0.01)
    sim.inject("loss", 30)  # a lossy link: lost LOG_DATA are asked for again
    sim.inject("silence")  # a WiFi drop: nothing either way until the agent sees it
    wait_until(
        "the agent saw the silence",
        lambda: v.agent.assessments()[sim.name].level.value != "OK",
        10,
        0.02,
    )
    sim.clear("silence")
    booted = sim.snapshot().time_boot_ms
    sim.inject("reboot", 0)  # the autopilot forgets the transfer; the card keeps the log
    wait_until("rebooted", lambda: sim.snapshot().time_boot_ms < booted, 10, 0.05)
    cut_at = fetcher.bytes_fetched
    manifest = settled(recorder.root)
    sim.clear("loss")
    assert cut_at < len(sim.logs.logs[0].data)  # the cuts came in the middle
    assert manifest.state is FlightState.COMPLETE, manifest
    entry = manifest.file(f"autopilot-logs/{sim.name}/1.ulg")
    assert entry is not None and entry.state is FileState.COMPLETE
    data = (recorder.root / manifest.flight_id / entry.path).read_bytes()
    assert data == sim.logs.logs[0].data
    assert sim.logs.served_bytes > len(data)  # some of it was sent twice


@pytest.mark.parametrize(
    ("damage", "expected"),
    [("truncate", "truncated: the autopilot's file ends at byte"), ("corrupt", "not a ULog")],
)
def test_a_damaged_autopilot_log_fails_that_file_and_touches_nothing_else(
    recorded: tuple[HubVehicle, FlightRecorder], damage: str, expected: str
) -> None:
    v, recorder = recorded
    px4, ardupilot = v.sims
    px4.logs.damage_next = damage
    fly_once(v)
    manifest = settled(recorder.root)
    assert manifest.state is FlightState.FAILED
    bad = manifest.file(f"autopilot-logs/{px4.name}/1.ulg")
    assert bad is not None and bad.state is FileState.FAILED
    assert expected in bad.message
    assert manifest.message.startswith(f"{bad.path}: ")
    others = [f for f in manifest.files if f.path != bad.path]
    assert {f.state for f in others} == {FileState.COMPLETE}
    assert manifest.file(f"autopilot-logs/{ardupilot.name}/1.bin") is not None


def _old_flight(root: Path, minutes_ago: int, size: int) -> str:
    armed = datetime.now(UTC) - timedelta(minutes=minutes_ago)
    manifest = Manifest(flight_id("v1", armed, ()), "v1", armed, armed, FlightState.COMPLETE)
    (root / manifest.flight_id).mkdir(parents=True)
    (root / manifest.flight_id / "hub.tlog").write_bytes(bytes(size))
    write_manifest(root, manifest)
    return manifest.flight_id


def test_a_flight_over_the_disk_budget_fails_and_the_vehicle_flies_on(tmp_path: Path) -> None:
    root = tmp_path / "records"
    oldest, older = _old_flight(root, 60, 20_000), _old_flight(root, 30, 20_000)
    with hub_vehicle(["px4", "px4"]) as v:
        recorder = FlightRecorder(v.agent, root, budget_bytes=60_000, budget_check_s=0.2)
        recorder.start()
        try:
            assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
            wait_until(
                "the flight over budget",
                lambda: read_manifests(root)[0].state is FlightState.FAILED,
                30,
            )
            # the oldest went first, then the next; the current one is kept, Failed
            assert [m.flight_id for m in read_manifests(root)] == [recorder.current]
            assert not (root / oldest).exists() and not (root / older).exists()
            failed = read_manifests(root)[0]
            assert "disk budget of 0.06 MB is reached by this flight alone" in failed.message
            # flying is untouched: the hub routes, commands are answered, health holds
            assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
            wait_until("disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 5)
            assert {a.level.value for a in v.agent.assessments().values()} == {"OK"}
            wait_until("landed", lambda: read_manifests(root)[0].disarmed_at is not None, 5)
            landed = read_manifests(root)[0]
            assert landed.state is FlightState.FAILED and landed.dropped["tlog"] > 0
        finally:
            recorder.stop()


def test_a_full_disk_fails_the_flight_with_why_and_the_vehicle_flies_on(
    recorded: tuple[HubVehicle, FlightRecorder],
) -> None:
    v, recorder = recorded
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    wait_until("recording", lambda: read_manifests(recorder.root), 5)
    # The one stand-in: the flight's tlog is swapped for /dev/full (a real device whose
    # every write fails with ENOSPC), as filling a real filesystem would need a mount.
    flight = recorder._flight
    assert flight is not None and flight.tlog is not None
    flight.tlog = Path("/dev/full").open("ab", buffering=0)  # noqa: SIM115
    wait_until(
        "the flight failed",
        lambda: read_manifests(recorder.root)[0].state is FlightState.FAILED,
        10,
    )
    assert "the disk is full" in read_manifests(recorder.root)[0].message
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
    wait_until("disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 5)
    assert {a.level.value for a in v.agent.assessments().values()} == {"OK"}


def test_a_second_flight_fetches_only_its_own_logs(
    recorded: tuple[HubVehicle, FlightRecorder],
) -> None:
    v, recorder = recorded
    fly_once(v)
    first = settled(recorder.root)
    fly_once(v)

    def second_settled() -> Manifest | None:
        found = read_manifests(recorder.root)
        done = (FlightState.COMPLETE, FlightState.FAILED)
        return found[0] if len(found) == 2 and found[0].state in done else None

    second = wait_until("the second flight settled", second_settled, 30)
    assert first.state is second.state is FlightState.COMPLETE
    logs = sorted(f.path for f in second.files if f.autopilot and f.path.startswith("autopilot"))
    px4, ardupilot = v.sims
    assert logs == [f"autopilot-logs/{px4.name}/2.ulg", f"autopilot-logs/{ardupilot.name}/2.bin"]


def test_a_flight_that_would_take_the_disk_below_its_reserve_fails_and_the_vehicle_flies_on(
    tmp_path: Path,
) -> None:
    """The reserve is the whole disk here (keep_free 1.0: no filesystem has that much
    free), so the first budget check finds no room: the real disk's figures, no stand-in."""
    root = tmp_path / "records"
    with hub_vehicle(["px4", "px4"]) as v:
        recorder = FlightRecorder(
            v.agent, root, budget_bytes=10**12, budget_check_s=0.2, keep_free=1.0
        )
        recorder.start()
        try:
            assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
            wait_until(
                "the flight failed",
                lambda: (
                    read_manifests(root) and read_manifests(root)[0].state is FlightState.FAILED
                ),
                30,
            )
            failed = read_manifests(root)[0]
            assert failed.message.startswith("the disk is nearly full: it keeps 100% free")
            assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
            wait_until("disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 5)
            assert {a.level.value for a in v.agent.assessments().values()} == {"OK"}
        finally:
            recorder.stop()


def test_a_log_download_whose_autopilot_never_comes_back_fails_with_how_much_came(
    tmp_path: Path,
) -> None:
    """The WiFi drop outlasts the fetcher's patience (1 s here, 30 s by default): that
    log is Failed with how much came, and the next autopilot's log is still fetched."""
    with hub_vehicle(["px4", "px4"]) as v:
        settings = FetchSettings(
            rate_bytes_per_s=2500, window=450, request_timeout_s=0.2, give_up_s=1.0
        )
        fetcher = LogFetcher(lambda: v.agent.links, settings=settings)
        recorder = FlightRecorder(
            v.agent, tmp_path / "records", budget_bytes=50_000_000, fetch_logs=fetcher
        )
        recorder.start()
        try:
            gone, other = v.sims
            fly_once(v)
            wait_until("the download started", lambda: fetcher.bytes_fetched > 0, 10, 0.01)
            gone.inject("silence")  # out of range for good
            manifest = settled(recorder.root)
        finally:
            recorder.stop()
    assert manifest.state is FlightState.FAILED
    lost = manifest.file(f"autopilot-logs/{gone.name}/1.ulg")
    assert lost is not None and lost.state is FileState.FAILED
    assert lost.message.startswith("the autopilot sent nothing for 1 s (")
    assert f"of {len(gone.logs.logs[0].data)} bytes fetched)" in lost.message
    assert manifest.message.startswith(f"{lost.path}: the autopilot sent nothing")
    fetched = manifest.file(f"autopilot-logs/{other.name}/1.ulg")
    assert fetched is not None and fetched.state is FileState.COMPLETE


def test_a_disk_full_during_a_log_download_fails_that_log_and_the_next_is_fetched(
    recorded: tuple[HubVehicle, FlightRecorder],
) -> None:
    v, recorder = recorded
    px4, ardupilot = v.sims
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    # the flight's directory is the recorder's to make: wait for its manifest in it
    flight = wait_until("recording", lambda: recorder.current, 5)
    wait_until("the flight's manifest", (recorder.root / flight / MANIFEST).exists, 5)
    # The one stand-in, as in the full-disk test above: the PX4 log's file is a link to
    # /dev/full (a real device whose every write fails with ENOSPC).
    target = recorder.root / flight / f"autopilot-logs/{px4.name}/1.ulg"
    target.parent.mkdir(parents=True)
    target.symlink_to("/dev/full")
    wait_until(
        "a second of samples logged",
        lambda: all(s.logs.samples_logging >= SAMPLES for s in v.sims),
        10,
    )
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
    manifest = settled(recorder.root)
    assert manifest.state is FlightState.FAILED
    full = manifest.file(f"autopilot-logs/{px4.name}/1.ulg")
    assert full is not None and full.state is FileState.FAILED
    assert full.message.startswith("the disk is full (0 of ")
    assert manifest.message.startswith(f"{full.path}: the disk is full")
    fetched = manifest.file(f"autopilot-logs/{ardupilot.name}/1.bin")
    assert fetched is not None and fetched.state is FileState.COMPLETE
    assert {a.level.value for a in v.agent.assessments().values()} == {"OK"}


def test_the_agents_own_log_download_stays_with_the_agent_and_a_clients_is_answered(
    recorded: tuple[HubVehicle, FlightRecorder],
) -> None:
    """LOG_ENTRY and LOG_DATA carry no target; the hub sends them where the request came
    from, as routing by target would: the agent's download to the agent alone, a ground
    station's own request to the ground station."""
    v, recorder = recorded
    fly_once(v)
    manifest = settled(recorder.root)
    assert manifest.state is FlightState.COMPLETE, manifest
    assert any(f.path.startswith("autopilot-logs/") for f in manifest.files)
    assert v.client.messages("LOG_ENTRY") == []
    assert v.client.messages("LOG_DATA") == []
    assert v.agent.hub is not None and v.agent.hub.counters.kept_for_agent > 0

    since = time.monotonic()
    v.client.mav.log_request_list_send(VEHICLE_SYSID, 1, 0, 0xFFFF)
    entry = v.client.wait_for(lambda r: r.kind == "LOG_ENTRY", 5, since).msg
    v.client.mav.log_request_data_send(VEHICLE_SYSID, 1, int(entry.id), 0, 90)
    data = v.client.wait_for(lambda r: r.kind == "LOG_DATA", 5, since).msg
    assert (int(data.id), int(data.ofs), int(data.count)) == (int(entry.id), 0, 90)
    v.client.mav.log_request_end_send(VEHICLE_SYSID, 1)
