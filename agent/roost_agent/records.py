"""Flight records on the vehicle: the directory layout, the manifest, the disk budget.

Every flight (first autopilot armed to the last one disarmed) leaves one directory under
the records directory, named ``<vehicle>-<UTC arm time>`` (``-2``, ``-3`` on a clash):

- ``flight.json``: the manifest (:class:`Manifest`), rewritten atomically (a temporary
  file renamed over it), so a reader or a power cut never sees half of one;
- ``hub.tlog``: the vehicle's MAVLink traffic (:mod:`roost_agent.records_recorder`);
- ``decisions.jsonl``: the agent's own events, one per line;
- ``params/<autopilot>.json``: each autopilot's parameters at arming;
- ``autopilot-logs/<autopilot>/<logId>.<ulg|bin>``: the autopilots' own logs, fetched
  after landing (:mod:`roost_agent.records_logs`).

This module holds the pure parts (names, the manifest's JSON, which flights the budget
deletes, HTTP ranges, which paths may be served) and the few file operations the
recorder, the log fetcher and the HTTP server (:mod:`roost_agent.records_server`) share,
so each rule lives in one place and is tested by a table.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from roost_api.records import FileKind, FileState, FlightState

MANIFEST = "flight.json"
TLOG = "hub.tlog"
DECISIONS = "decisions.jsonl"
PARAMS_DIR = "params"
LOGS_DIR = "autopilot-logs"
DEFAULT_PORT = 9468
DEFAULT_DIR = "/var/lib/roost/records"
DEFAULT_BUDGET_MB = 1024
DEFAULT_KEEP_FREE_PERCENT = 15.0
"""The records never bring their filesystem below this much free (the kubelet's
default hard eviction threshold is 10 % free on the node's filesystem)."""

_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class FileEntry:
    """One file of a flight, as the manifest lists it (``path`` relative to the flight)."""

    path: str
    kind: FileKind
    state: FileState = FileState.PARTIAL
    bytes: int = 0
    sha256: str | None = None
    autopilot: str | None = None
    message: str = ""

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "path": self.path,
            "bytes": self.bytes,
            "kind": self.kind.value,
            "state": self.state.value,
            "message": self.message,
        }
        if self.sha256 is not None:
            doc["sha256"] = self.sha256
        if self.autopilot is not None:
            doc["autopilot"] = self.autopilot
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> FileEntry:
        return cls(
            path=str(doc["path"]),
            kind=FileKind(doc["kind"]),
            state=FileState(doc.get("state", "Partial")),
            bytes=int(doc.get("bytes", 0)),
            sha256=doc.get("sha256"),
            autopilot=doc.get("autopilot"),
            message=str(doc.get("message", "")),
        )


@dataclass(frozen=True)
class Manifest:
    """``flight.json``: what the flight is and which files it has, in what state."""

    flight_id: str
    vehicle: str
    armed_at: datetime
    disarmed_at: datetime | None = None
    state: FlightState = FlightState.RECORDING
    message: str = ""
    files: tuple[FileEntry, ...] = ()
    dropped: dict[str, int] = field(default_factory=lambda: {"tlog": 0, "decisions": 0})

    def with_file(self, entry: FileEntry) -> Manifest:
        """This manifest with ``entry`` added, or replacing the entry of the same path."""
        files = (*(f for f in self.files if f.path != entry.path), entry)
        return replace(self, files=files)

    def file(self, path: str) -> FileEntry | None:
        return next((f for f in self.files if f.path == path), None)

    def failed(self, message: str) -> Manifest:
        """Failed keeps the first failure's message (the cause, not a consequence)."""
        if self.state is FlightState.FAILED:
            return self
        return replace(self, state=FlightState.FAILED, message=message)

    def settled(self) -> Manifest:
        """A landed flight whose files are all written: Complete, or Failed with the
        first failed file's message."""
        if self.state is not FlightState.LANDED:
            return self
        failed = next((f for f in self.files if f.state is FileState.FAILED), None)
        if failed is not None:
            return self.failed(f"{failed.path}: {failed.message}")
        return replace(self, state=FlightState.COMPLETE)

    def to_json(self) -> dict[str, Any]:
        return {
            "flightId": self.flight_id,
            "vehicle": self.vehicle,
            "armedAt": _iso(self.armed_at),
            "disarmedAt": None if self.disarmed_at is None else _iso(self.disarmed_at),
            "state": self.state.value,
            "message": self.message,
            "files": [f.to_json() for f in self.files],
            "dropped": dict(self.dropped),
        }

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Manifest:
        disarmed = doc.get("disarmedAt")
        return cls(
            flight_id=str(doc["flightId"]),
            vehicle=str(doc["vehicle"]),
            armed_at=_parse_iso(str(doc["armedAt"])),
            disarmed_at=None if disarmed is None else _parse_iso(str(disarmed)),
            state=FlightState(doc.get("state", "Recording")),
            message=str(doc.get("message", "")),
            files=tuple(FileEntry.from_json(f) for f in doc.get("files", [])),
            dropped={str(k): int(v) for k, v in (doc.get("dropped") or {}).items()},
        )


def _iso(when: datetime) -> str:
    return when.astimezone(UTC).isoformat().replace("+00:00", "Z")


def _parse_iso(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


def flight_id(vehicle: str, armed_at: datetime, existing: Iterable[str]) -> str:
    """``<vehicle>-<YYYYmmddTHHMMSSZ>``, with ``-2``, ``-3``... when that name is taken
    (two arms within a second, or a clock that went back)."""
    base = f"{vehicle}-{armed_at.astimezone(UTC).strftime('%Y%m%dT%H%M%SZ')}"
    taken = set(existing)
    if base not in taken:
        return base
    n = 2
    while f"{base}-{n}" in taken:
        n += 1
    return f"{base}-{n}"


# -- the disk budget ------------------------------------------------------------------


@dataclass(frozen=True)
class StoredFlight:
    """A flight directory as the budget sees it."""

    flight_id: str
    armed_at: datetime
    bytes: int


@dataclass(frozen=True)
class BudgetChoice:
    """What the budget asks: delete these flights (oldest first); ``fits`` False when
    even that leaves the records over budget (the current flight alone is too big)."""

    delete: tuple[str, ...]
    fits: bool


def choose_deletions(
    flights: Sequence[StoredFlight], current: str | None, budget_bytes: int
) -> BudgetChoice:
    """The oldest flights to delete until the records fit ``budget_bytes``; the current
    flight is never deleted."""
    total = sum(f.bytes for f in flights)
    delete: list[str] = []
    for flight in sorted(flights, key=lambda f: (f.armed_at, f.flight_id)):
        if total <= budget_bytes:
            break
        if flight.flight_id == current:
            continue
        delete.append(flight.flight_id)
        total -= flight.bytes
    return BudgetChoice(tuple(delete), total <= budget_bytes)


def budget_within_disk(
    budget_bytes: int,
    records_bytes: int,
    free_bytes: int,
    disk_bytes: int,
    keep_free: float,
) -> tuple[int, bool]:
    """The budget the disk allows, and whether the disk (not ``budget_bytes``) set it.

    The records may grow only while the filesystem keeps ``keep_free`` (a fraction of
    ``disk_bytes``) free: on a vehicle's SD card the kubelet starts evicting pods, the
    agent's among them, when the node's filesystem falls below 10 % free, and the
    container runtime and the system need the same card. So the records get at most what
    they hold now plus the free space above that reserve."""
    reserve = int(disk_bytes * keep_free)
    room = max(records_bytes + free_bytes - reserve, 0)
    if room < budget_bytes:
        return room, True
    return budget_bytes, False


def directory_bytes(path: Path) -> int:
    """Bytes of the files under ``path`` (0 for a path that vanished meanwhile)."""
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += (Path(root) / name).stat().st_size
    return total


def stored_flights(root: Path) -> list[StoredFlight]:
    """Every flight directory under ``root`` with a readable manifest."""
    out: list[StoredFlight] = []
    for manifest in read_manifests(root):
        out.append(
            StoredFlight(
                manifest.flight_id, manifest.armed_at, directory_bytes(root / manifest.flight_id)
            )
        )
    return out


def delete_flight(root: Path, flight: str) -> None:
    if valid_flight_id(flight):
        shutil.rmtree(root / flight, ignore_errors=True)


# -- manifests on disk ----------------------------------------------------------------


def write_manifest(root: Path, manifest: Manifest) -> None:
    """Write ``flight.json`` atomically (a reader sees the old or the new one, whole)."""
    directory = root / manifest.flight_id
    tmp = directory / f".{MANIFEST}.tmp"
    data = json.dumps(manifest.to_json(), indent=1).encode()
    with tmp.open("wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
    tmp.replace(directory / MANIFEST)
    fsync_directory(directory)


def fsync_directory(directory: Path) -> None:
    """Make a rename or a new file in ``directory`` survive a power cut."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_manifest(root: Path, flight: str) -> Manifest | None:
    if not valid_flight_id(flight):
        return None
    try:
        return Manifest.from_json(json.loads((root / flight / MANIFEST).read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def read_manifests(root: Path) -> list[Manifest]:
    """Every readable manifest under ``root``, newest arm time first."""
    try:
        names = [p.name for p in root.iterdir() if p.is_dir()]
    except OSError:
        return []
    found = [m for m in (read_manifest(root, n) for n in names) if m is not None]
    found.sort(key=lambda m: (m.armed_at, m.flight_id), reverse=True)
    return found


# -- serving ---------------------------------------------------------------------------


def valid_flight_id(text: str) -> bool:
    return bool(_ID_PATTERN.match(text)) and ".." not in text


def resolve_record(root: Path, flight: str, path: str) -> Path | None:
    """The file ``path`` of ``flight`` under ``root``, or None when it is not one (an
    unknown flight, a path that leaves the flight directory, a directory, a hidden
    temporary file)."""
    if not valid_flight_id(flight) or not path:
        return None
    parts = path.split("/")
    if any(p in ("", ".", "..") or p.startswith(".") or "\\" in p for p in parts):
        return None
    base = (root / flight).resolve()
    target = (base / path).resolve()
    if base not in target.parents or not target.is_file():
        return None
    return target


@dataclass(frozen=True)
class ByteRange:
    start: int
    end: int  # inclusive

    @property
    def length(self) -> int:
        return self.end - self.start + 1


class RangeNotSatisfiableError(ValueError):
    """A range that starts beyond the file (HTTP 416)."""


def parse_range(header: str | None, size: int) -> ByteRange | None:
    """The single range of a ``Range: bytes=N-[M]`` header for a file of ``size`` bytes;
    None means the whole file (no header, or one this server does not honour: several
    ranges, another unit, a malformed one, which HTTP allows answering with 200).
    Raises :class:`RangeNotSatisfiableError` for a start at or past the end."""
    if header is None:
        return None
    unit, sep, spec = header.strip().partition("=")
    if not sep or unit.strip().lower() != "bytes" or "," in spec:
        return None
    first, dash, last = spec.strip().partition("-")
    if not dash:
        return None
    try:
        suffix = int(last) if first == "" else None  # bytes=-N: the last N bytes
        start = 0 if suffix is not None else int(first)
        end = int(last) if last else size - 1
    except ValueError:
        return None
    if suffix is not None:
        if suffix <= 0:
            raise RangeNotSatisfiableError(header)
        return ByteRange(max(0, size - suffix), size - 1) if size else None
    if start >= size:
        raise RangeNotSatisfiableError(header)
    if end < start:
        return None
    return ByteRange(start, min(end, size - 1))
