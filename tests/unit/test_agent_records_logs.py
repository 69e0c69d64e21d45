"""Flight recording's pure parts: when a flight is on, the tap, the tlog record, the
resumable download's planner and the autopilot log format checks."""

from __future__ import annotations

import io
import struct

import pytest
import pyulog

from roost_agent.records_logs import (
    Intervals,
    check_dataflash,
    check_ulog,
    logs_to_fetch,
    next_request,
)
from roost_agent.records_recorder import FrameTap, frame_source, in_flight, tlog_record
from roost_sim.logs import Sample, dataflash_bytes, ulog_bytes

NOW = 100.0
ARMED, DISARMED = True, False

# flying, heartbeats (armed, received at) per autopilot -> flying
FLIGHT_TABLE: list[tuple[bool, list[tuple[bool, float] | None], bool]] = [
    # on the ground
    (False, [(DISARMED, NOW), (DISARMED, NOW)], False),
    (False, [None, None], False),
    # any fresh armed heartbeat starts a flight (a standby armed alone too)
    (False, [(ARMED, NOW), (DISARMED, NOW)], True),
    (False, [(DISARMED, NOW), (ARMED, NOW - 1)], True),
    # a stale armed heartbeat does not (an autopilot that died armed long ago)
    (False, [(ARMED, NOW - 10), (DISARMED, NOW)], False),
    # in flight: goes on while any fresh one is armed
    (True, [(ARMED, NOW), (DISARMED, NOW)], True),
    # ends when every fresh one says disarmed, a dead one (stale, armed) ignored
    (True, [(DISARMED, NOW), (DISARMED, NOW)], False),
    (True, [(ARMED, NOW - 10), (DISARMED, NOW)], False),
    # every link silent: nothing known, the flight goes on
    (True, [(ARMED, NOW - 10), (ARMED, NOW - 10)], True),
    (True, [None, (ARMED, NOW - 10)], True),
    (True, [None, None], True),
]


@pytest.mark.parametrize(("flying", "beats", "expected"), FLIGHT_TABLE)
def test_a_flight_is_the_armed_interval_of_the_vehicle(
    flying: bool, beats: list[tuple[bool, float] | None], expected: bool
) -> None:
    assert in_flight(flying, beats, NOW) is expected


def test_the_tap_drops_and_counts_when_full_and_never_blocks() -> None:
    tap = FrameTap(capacity=3)
    for n in range(5):
        tap(bytes([n]))
    assert tap.dropped == 2
    assert [frame for _, frame in tap.drain()] == [b"\0", b"\1", b"\2"]
    tap(b"\3")
    assert [frame for _, frame in tap.drain()] == [b"\3"]
    assert tap.dropped == 2


def test_a_tlog_record_is_the_big_endian_microsecond_time_then_the_frame() -> None:
    record = tlog_record(1_700_000_000.25, b"\xfd\x01")
    assert record == struct.pack(">Q", 1_700_000_000_250_000) + b"\xfd\x01"


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        (bytes([0xFD, 25, 0, 0, 7, 42, 1, 22, 0, 0]) + bytes(27), (42, 22)),
        (bytes([0xFE, 9, 7, 42, 1, 0]) + bytes(11), (42, 0)),
        (b"\x00" * 12, None),
        (b"\xfd\x01", None),
    ],
)
def test_frame_source(frame: bytes, expected: tuple[int, int] | None) -> None:
    assert frame_source(frame) == expected


# arrived spans, size, window -> next request
PLAN_TABLE: list[tuple[list[tuple[int, int]], int, int, tuple[int, int] | None]] = [
    ([], 1000, 450, (0, 450)),  # nothing yet: the first window
    ([(0, 450)], 1000, 450, (450, 450)),
    ([(0, 900)], 1000, 450, (900, 100)),  # the last, short window
    ([(0, 1000)], 1000, 450, None),  # whole
    ([(0, 90), (180, 1000)], 1000, 450, (90, 90)),  # one lost LOG_DATA: only it again
    ([(90, 1000)], 1000, 450, (0, 90)),
    ([(0, 90), (180, 270), (450, 1000)], 1000, 450, (90, 90)),  # the first gap first
    ([(0, 1200)], 1000, 450, None),  # more than listed (ignored)
    ([], 0, 450, None),  # an empty log
]


@pytest.mark.parametrize(("spans", "size", "window", "expected"), PLAN_TABLE)
def test_the_download_asks_only_for_what_is_missing(
    spans: list[tuple[int, int]], size: int, window: int, expected: tuple[int, int] | None
) -> None:
    have = Intervals()
    for start, end in spans:
        have.add(start, end)
    assert next_request(have, size, window) == expected


def test_intervals_merge_overlapping_and_adjacent_pieces_in_any_order() -> None:
    have = Intervals()
    for start, end in [(180, 270), (0, 90), (90, 180), (500, 600), (550, 650), (10, 20)]:
        have.add(start, end)
    assert have.spans == [(0, 270), (500, 650)]
    assert have.covered() == 420
    assert have.missing(700) == [(270, 500), (650, 700)]


LISTED = {1: (0, 10), 2: (0, 20), 3: (1_700_000_000, 30), 4: (0, 40), 5: (0, 50)}

# listed logs, the last id fetched from this autopilot -> the logs fetched now
FETCH_TABLE: list[tuple[dict[int, tuple[int, int]], int | None, list[int]]] = [
    (LISTED, None, [5]),  # nothing fetched before: the newest alone
    (LISTED, 4, [5]),  # one new log: this flight's
    (LISTED, 3, [4, 5]),  # a reboot in flight started a second log
    (LISTED, 0, [3, 4, 5]),  # many new ones: the newest three (older flights unseen)
    (LISTED, 5, []),  # no log after it: the autopilot did not log this flight
    (LISTED, 9, [5]),  # the card was wiped and numbers again from 1
    ({}, 3, []),  # no log at all
]


@pytest.mark.parametrize(("listed", "last", "expected"), FETCH_TABLE)
def test_the_logs_of_the_flight_are_those_after_the_last_fetched(
    listed: dict[int, tuple[int, int]], last: int | None, expected: list[int]
) -> None:
    assert logs_to_fetch(listed, last) == [(i, listed[i][1]) for i in expected]


def _samples(n: int = 20) -> list[Sample]:
    return [
        Sample(
            1_000_000 + i * 100_000,
            1_700_000_000_000_000 + i * 100_000,
            i * 0.1,
            0.0,
            i * 0.2,
            0.5,
            True,
            4,
            "GUIDED",
        )
        for i in range(n)
    ]


ULOG = ulog_bytes(_samples(), {"MPC_XY_VEL_MAX": 12.0, "SYS_AUTOSTART": 4001})
DATAFLASH = dataflash_bytes(_samples(), {"WPNAV_SPEED": 500.0}, (47.0, 8.0))


def test_the_simulators_ulog_is_read_by_pyulog_as_px4_logs_are() -> None:
    """pyulog (what PX4 Flight Review and ulog2csv use) reads the simulator's log whole:
    no corruption, the parameters with their types, every sample of both topics."""
    log = pyulog.ULog(io.BytesIO(ULOG))
    assert not log.file_corruption
    assert log.initial_parameters == {"MPC_XY_VEL_MAX": 12, "SYS_AUTOSTART": 4001}
    topics = {data.name: len(data.data["timestamp"]) for data in log.data_list}
    assert topics == {"vehicle_local_position": len(_samples()), "vehicle_status": 1}
    assert [m.message for m in log.logged_messages] == ["Armed by the agent", "Disarmed"]


def test_whole_logs_pass_their_checks() -> None:
    assert check_ulog(ULOG) is None
    assert check_dataflash(DATAFLASH) is None


@pytest.mark.parametrize(
    ("data", "check", "expected"),
    [
        (ULOG[: len(ULOG) - 5], check_ulog, "truncated ULog"),
        (ULOG[:17], check_ulog, "truncated ULog"),
        (b"\xff" * 16 + ULOG[16:], check_ulog, "not a ULog"),
        (ULOG[:10], check_ulog, "not a ULog"),
        (DATAFLASH[: len(DATAFLASH) - 5], check_dataflash, "truncated DataFlash"),
        (b"\xff" * 16 + DATAFLASH[16:], check_dataflash, "not a DataFlash"),
        (DATAFLASH[:89] + b"\x00\x00" + DATAFLASH[91:], check_dataflash, "no record header"),
    ],
)
def test_damaged_logs_are_named_with_where(data: bytes, check: object, expected: str) -> None:
    assert callable(check)
    problem = check(data)
    assert problem is not None and expected in problem
