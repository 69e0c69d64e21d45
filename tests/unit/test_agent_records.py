"""Flight records: names, manifests, the disk budget's choice, HTTP ranges, served paths."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from roost_agent.records import (
    ByteRange,
    FileEntry,
    Manifest,
    RangeNotSatisfiableError,
    StoredFlight,
    budget_within_disk,
    choose_deletions,
    flight_id,
    parse_range,
    read_manifests,
    resolve_record,
    write_manifest,
)
from roost_agent.records_recorder import close_interrupted
from roost_api.records import FileKind, FileState, FlightState

T0 = datetime(2026, 11, 27, 20, 0, 0, tzinfo=UTC)


@pytest.mark.parametrize(
    ("existing", "expected"),
    [
        ((), "drone1-20261127T200000Z"),
        (("drone1-20261127T200000Z",), "drone1-20261127T200000Z-2"),
        (("drone1-20261127T200000Z", "drone1-20261127T200000Z-2"), "drone1-20261127T200000Z-3"),
        (("drone1-20261127T195959Z",), "drone1-20261127T200000Z"),
    ],
)
def test_flight_id_is_the_arm_time_with_a_suffix_on_a_clash(
    existing: tuple[str, ...], expected: str
) -> None:
    assert flight_id("drone1", T0, existing) == expected


def _flight(name: str, minutes: int, size: int) -> StoredFlight:
    return StoredFlight(name, T0 + timedelta(minutes=minutes), size)


# flights (name, minutes after T0, bytes), current, budget -> deleted, fits
BUDGET_TABLE = [
    # under budget: nothing goes
    ([("a", 0, 10), ("b", 1, 10)], "b", 30, (), True),
    # exactly at the budget: nothing goes
    ([("a", 0, 10), ("b", 1, 20)], "b", 30, (), True),
    # over: the oldest goes first, only as many as needed
    ([("a", 0, 10), ("b", 1, 10), ("c", 2, 10)], "c", 25, ("a",), True),
    ([("a", 0, 10), ("b", 1, 10), ("c", 2, 10)], "c", 15, ("a", "b"), True),
    # order is the arm time, not the listing order
    ([("c", 2, 10), ("a", 0, 10), ("b", 1, 10)], None, 20, ("a",), True),
    # the current flight is never deleted, even when it is the oldest (clock went back)
    ([("cur", 0, 10), ("b", 1, 10)], "cur", 15, ("b",), True),
    # the current flight alone is over budget: every other goes and it still does not fit
    ([("a", 0, 10), ("cur", 1, 50)], "cur", 30, ("a",), False),
    # no flight in the air: the newest goes too when it has to
    ([("a", 0, 10), ("b", 1, 50)], None, 30, ("a", "b"), True),
    # zero budget with a flight in the air
    ([("cur", 0, 1)], "cur", 0, (), False),
]


@pytest.mark.parametrize(("flights", "current", "budget", "deleted", "fits"), BUDGET_TABLE)
def test_the_budget_deletes_the_oldest_flights_but_never_the_current_one(
    flights: list[tuple[str, int, int]],
    current: str | None,
    budget: int,
    deleted: tuple[str, ...],
    fits: bool,
) -> None:
    choice = choose_deletions([_flight(*f) for f in flights], current, budget)
    assert choice.delete == deleted
    assert choice.fits is fits


# header, size -> range (None: the whole file) or 416
RANGE_TABLE: list[tuple[str | None, int, ByteRange | type[RangeNotSatisfiableError] | None]] = [
    (None, 100, None),
    ("bytes=0-", 100, ByteRange(0, 99)),
    ("bytes=40-", 100, ByteRange(40, 99)),
    ("bytes=40-49", 100, ByteRange(40, 49)),
    ("bytes=40-1000", 100, ByteRange(40, 99)),
    ("bytes=-10", 100, ByteRange(90, 99)),
    ("bytes=-1000", 100, ByteRange(0, 99)),
    ("bytes=99-", 100, ByteRange(99, 99)),
    ("bytes=100-", 100, RangeNotSatisfiableError),
    ("bytes=0-", 0, RangeNotSatisfiableError),
    ("bytes=-0", 100, RangeNotSatisfiableError),
    # not honoured: served whole (HTTP allows it)
    ("bytes=0-1,5-6", 100, None),
    ("items=0-", 100, None),
    ("bytes=x-", 100, None),
    ("bytes=50-40", 100, None),
    ("bytes", 100, None),
]


@pytest.mark.parametrize(("header", "size", "expected"), RANGE_TABLE)
def test_range_headers(
    header: str | None, size: int, expected: ByteRange | type[RangeNotSatisfiableError] | None
) -> None:
    if expected is RangeNotSatisfiableError:
        with pytest.raises(RangeNotSatisfiableError):
            parse_range(header, size)
    else:
        assert parse_range(header, size) == expected


def test_manifest_round_trips_and_is_written_whole(tmp_path: Path) -> None:
    manifest = Manifest("v-20261127T200000Z", "v", T0).with_file(
        FileEntry("hub.tlog", FileKind.TLOG, FileState.PARTIAL, 10)
    )
    manifest = manifest.with_file(
        FileEntry("hub.tlog", FileKind.TLOG, FileState.COMPLETE, 20, sha256="ab")
    )
    (tmp_path / manifest.flight_id).mkdir()
    write_manifest(tmp_path, manifest)
    [read] = read_manifests(tmp_path)
    assert read == manifest
    doc = read.to_json()
    assert doc["disarmedAt"] is None
    assert doc["armedAt"] == "2026-11-27T20:00:00Z"
    assert doc["files"] == [
        {
            "path": "hub.tlog",
            "bytes": 20,
            "kind": "tlog",
            "state": "Complete",
            "message": "",
            "sha256": "ab",
        }
    ]
    assert doc["dropped"] == {"tlog": 0, "decisions": 0}
    assert [p.name for p in (tmp_path / manifest.flight_id).iterdir()] == ["flight.json"]


def test_failed_keeps_the_first_cause() -> None:
    manifest = Manifest("f", "v", T0).failed("disk full").failed("a consequence")
    assert (manifest.state, manifest.message) == (FlightState.FAILED, "disk full")


def test_manifests_are_listed_newest_first_and_unreadable_ones_skipped(tmp_path: Path) -> None:
    for minutes in (0, 5, 2):
        m = Manifest(
            flight_id("v", T0 + timedelta(minutes=minutes), ()),
            "v",
            T0 + timedelta(minutes=minutes),
        )
        (tmp_path / m.flight_id).mkdir()
        write_manifest(tmp_path, m)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "flight.json").write_text("{not json")
    assert [m.armed_at.minute for m in read_manifests(tmp_path)] == [5, 2, 0]


@pytest.mark.parametrize(
    ("flight", "path", "served"),
    [
        ("f1", "hub.tlog", True),
        ("f1", "autopilot-logs/fc1/1.ulg", True),
        ("f1", "../f2/hub.tlog", False),
        ("f1", "autopilot-logs/../../f2/hub.tlog", False),
        ("..", "f2/hub.tlog", False),
        ("f1", "/etc/passwd", False),
        ("f1", "autopilot-logs", False),  # a directory
        ("f1", ".flight.json.tmp", False),  # a temporary file
        ("f1", "missing", False),
        ("f9", "hub.tlog", False),
        ("f1", "link", False),  # a symlink out of the flight
        ("f1", "", False),
    ],
)
def test_only_files_inside_the_flight_are_served(
    tmp_path: Path, flight: str, path: str, served: bool
) -> None:
    root = tmp_path / "records"
    (root / "f1" / "autopilot-logs" / "fc1").mkdir(parents=True)
    (root / "f2").mkdir()
    for name in (
        "f1/hub.tlog",
        "f1/autopilot-logs/fc1/1.ulg",
        "f2/hub.tlog",
        "f1/.flight.json.tmp",
    ):
        (root / name).write_bytes(b"x")
    (tmp_path / "secret").write_bytes(b"s")
    (root / "f1" / "link").symlink_to(tmp_path / "secret")
    assert (resolve_record(root, flight, path) is not None) is served


def test_flights_interrupted_by_a_restart_are_closed_as_they_stand(tmp_path: Path) -> None:
    recording = Manifest("v-1", "v", T0).with_file(FileEntry("hub.tlog", FileKind.TLOG))
    landed = Manifest("v-2", "v", T0 + timedelta(minutes=1), state=FlightState.LANDED)
    landed = landed.with_file(
        FileEntry("autopilot-logs/fc1/3.ulg", FileKind.AUTOPILOT_LOG, autopilot="fc1")
    )
    done = Manifest("v-3", "v", T0 + timedelta(minutes=2), state=FlightState.COMPLETE)
    for manifest in (recording, landed, done):
        (tmp_path / manifest.flight_id).mkdir()
        write_manifest(tmp_path, manifest)
    (tmp_path / "v-1" / "hub.tlog").write_bytes(b"x" * 10)
    close_interrupted(tmp_path)
    after = {m.flight_id: m for m in read_manifests(tmp_path)}
    assert after["v-1"].state is FlightState.FAILED
    assert "stopped during the flight" in after["v-1"].message
    tlog = after["v-1"].file("hub.tlog")
    assert tlog is not None and (tlog.state, tlog.bytes) == (FileState.COMPLETE, 10)
    assert after["v-2"].state is FlightState.FAILED
    log = after["v-2"].file("autopilot-logs/fc1/3.ulg")
    assert log is not None and log.state is FileState.FAILED
    assert "download" in log.message
    assert after["v-3"] == done


MB = 1_000_000
# budget, records now, free, disk size, keep free -> (budget used, set by the disk)
DISK_TABLE = [
    ("a big card: the budget", 1024 * MB, 100 * MB, 20_000 * MB, 32_000 * MB, 0.15,
     (1024 * MB, False)),
    ("a small card: the reserve", 1024 * MB, 100 * MB, 1_500 * MB, 8_000 * MB, 0.15,
     (400 * MB, True)),
    ("records already fill the room", 1024 * MB, 600 * MB, 800 * MB, 8_000 * MB, 0.15,
     (200 * MB, True)),
    ("below the reserve already: none", 1024 * MB, 0, 500 * MB, 8_000 * MB, 0.15, (0, True)),
    ("no reserve", 1024 * MB, 0, 500 * MB, 8_000 * MB, 0.0, (500 * MB, True)),
    ("the whole disk reserved", 1024 * MB, 10 * MB, 500 * MB, 8_000 * MB, 1.0, (0, True)),
]  # fmt: skip


@pytest.mark.parametrize(
    ("figures", "expected"),
    [(case[1:-1], case[-1]) for case in DISK_TABLE],
    ids=[case[0] for case in DISK_TABLE],
)
def test_the_records_never_take_the_disk_below_its_reserve(
    figures: tuple[int, int, int, int, float], expected: tuple[int, bool]
) -> None:
    budget, records, free, disk, keep_free = figures
    assert budget_within_disk(budget, records, free, disk, keep_free) == expected
