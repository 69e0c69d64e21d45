"""Fetch the autopilots' own logs after landing, over the MAVLink log protocol.

Every autopilot of the vehicle, standbys included: a failover's story is in the log of
the autopilot that failed as much as in the one that took over. The protocol (common.xml
"log" messages, as PX4 and ArduPilot implement it): ``LOG_REQUEST_LIST`` gives one
``LOG_ENTRY`` per log (``num_logs 0``: none); ``LOG_REQUEST_DATA(id, ofs, count)`` makes
the autopilot stream ``LOG_DATA`` of up to 90 bytes at ``ofs``, ``count 0`` meaning
the file ends there; ``LOG_REQUEST_END`` lets it log again. The log of the flight that
just ended are those after the last one fetched from that autopilot (both stacks start
one per arming, and a reboot in flight starts another): :func:`logs_to_fetch`.

- Resumable: what arrived is kept as byte intervals (:class:`Intervals`), and the fetcher
  asks only for the missing ones (:func:`next_request`), a window at a time. A lost
  ``LOG_DATA``, a WiFi drop or an autopilot reboot in the middle costs a re-request of
  what is missing, not a restart.
- Paced: one window in flight, and the windows no faster than ``rate_bytes_per_s``, so
  the telemetry and the clients' traffic on the same link go on.
- Never while armed: checked before every window; arming aborts the download (the file
  stays with what arrived and says why).
- Checked: a finished file is walked record by record (:func:`check_ulog`,
  :func:`check_dataflash`); a corrupt or truncated log is marked Failed with where and
  why, and nothing else is touched.
"""

from __future__ import annotations

import errno
import logging
import os
import queue
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

from roost_agent.records import LOGS_DIR, FileEntry, Manifest, read_manifests
from roost_api.core import Stack
from roost_api.records import FileKind, FileState, sha256_of
from roost_mavlink import MAV_MODE_FLAG_SAFETY_ARMED

log = logging.getLogger(__name__)

LOG_DATA_BYTES = 90
WINDOW_BYTES = LOG_DATA_BYTES * 64
DEFAULT_RATE_BYTES_PER_S = 100_000.0
REQUEST_TIMEOUT_S = 1.0
LIST_TIMEOUT_S = 2.0
MAX_LOGS = 3  # logs of one autopilot fetched after one flight at most
GIVE_UP_S = 30.0  # no byte for this long (the autopilot gone): the log is not fetched
PROGRESS_EVERY_S = 2.0

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_HEAD = b"\xa3\x95"


# -- what arrived, what is missing (pure) ---------------------------------------------


@dataclass
class Intervals:
    """Disjoint, sorted ``[start, end)`` byte intervals that arrived."""

    spans: list[tuple[int, int]] = field(default_factory=list)

    def add(self, start: int, end: int) -> None:
        if end <= start:
            return
        merged: list[tuple[int, int]] = []
        for a, b in self.spans:
            if b < start or a > end:
                merged.append((a, b))
            else:
                start, end = min(a, start), max(b, end)
        merged.append((start, end))
        merged.sort()
        self.spans = merged

    def covered(self) -> int:
        return sum(b - a for a, b in self.spans)

    def missing(self, size: int) -> list[tuple[int, int]]:
        """The gaps in ``[0, size)``."""
        out: list[tuple[int, int]] = []
        at = 0
        for a, b in self.spans:
            if a > at:
                out.append((at, min(a, size)))
            at = max(at, b)
            if at >= size:
                break
        if at < size:
            out.append((at, size))
        return [(a, b) for a, b in out if b > a]


def next_request(have: Intervals, size: int, window: int) -> tuple[int, int] | None:
    """``(ofs, count)`` of the next LOG_REQUEST_DATA: the first gap, at most ``window``
    bytes of it; None when the file is whole."""
    gaps = have.missing(size)
    if not gaps:
        return None
    start, end = gaps[0]
    return start, min(end - start, window)


def logs_to_fetch(
    entries: Mapping[int, tuple[int, int]], last_fetched: int | None, limit: int = MAX_LOGS
) -> list[tuple[int, int]]:
    """``(id, size)`` of the logs of the flight that just ended, oldest first, among
    ``entries`` (id -> (time_utc, size)): those after the last one fetched from this
    autopilot (a reboot in flight starts a second log), at most ``limit``, the newest
    ones; none when no log came after it (the autopilot did not log this flight); the
    newest alone when none was fetched before or the card's numbering started again.
    Both stacks number logs upwards; the UTC time may be unset (0), so it is not used."""
    if not entries:
        return []
    if last_fetched is None or max(entries) < last_fetched:
        chosen = [max(entries)]
    else:
        chosen = sorted(i for i in entries if i > last_fetched)[-limit:]
    return [(i, entries[i][1]) for i in chosen]


def last_fetched(root: Path, exclude: str, autopilot: str) -> int | None:
    """The highest log id fetched whole from ``autopilot`` in the flights under
    ``root`` other than ``exclude``."""
    best: int | None = None
    for manifest in read_manifests(root):
        if manifest.flight_id == exclude:
            continue
        for f in manifest.files:
            if (
                f.kind is FileKind.AUTOPILOT_LOG
                and f.autopilot == autopilot
                and f.state is FileState.COMPLETE
            ):
                stem = Path(f.path).stem
                if stem.isdigit() and (best is None or int(stem) > best):
                    best = int(stem)
    return best


# -- format checks (pure) -------------------------------------------------------------


def check_ulog(data: bytes) -> str | None:
    """None for a ULog that is whole; else what is wrong and where."""
    if len(data) < 16 or not data.startswith(ULOG_MAGIC):
        return "not a ULog file: the header's magic bytes are wrong"
    at = 16
    formats: set[str] = set()
    subscribed: dict[int, str] = {}
    while at < len(data):
        if at + 3 > len(data):
            return f"truncated ULog: a message header is cut at byte {at} of {len(data)}"
        size, kind = struct.unpack_from("<HB", data, at)
        body = data[at + 3 : at + 3 + size]
        if len(body) < size:
            return f"truncated ULog: a message at byte {at} needs {size} bytes, {len(body)} left"
        letter = chr(kind)
        if letter == "F":
            formats.add(body.split(b":", 1)[0].decode("ascii", "replace"))
        elif letter == "A":
            name = body[3:].decode("ascii", "replace")
            if name not in formats:
                return f"corrupt ULog: byte {at} subscribes {name!r}, which has no format"
            subscribed[struct.unpack_from("<H", body, 1)[0]] = name
        elif letter == "D":
            if len(body) < 2 or struct.unpack_from("<H", body)[0] not in subscribed:
                return f"corrupt ULog: data at byte {at} for a message never subscribed"
        elif letter not in "BIMPQLCSOR":
            return f"corrupt ULog: unknown message type {kind} at byte {at}"
        at += 3 + size
    return None


def check_dataflash(data: bytes) -> str | None:
    """None for a DataFlash binary log that is whole; else what is wrong and where."""
    if len(data) < 3 or not data.startswith(DATAFLASH_HEAD) or data[2] != 128:
        return "not a DataFlash log: it does not start with an FMT record"
    lengths = {128: 89}
    at = 0
    while at < len(data):
        if data[at : at + 2] != DATAFLASH_HEAD:
            return f"corrupt DataFlash log: no record header at byte {at}"
        if at + 3 > len(data):
            return f"truncated DataFlash log: a record header is cut at byte {at}"
        kind = data[at + 2]
        length = lengths.get(kind)
        if length is None:
            return f"corrupt DataFlash log: record type {kind} at byte {at} has no FMT"
        if at + length > len(data):
            return (
                f"truncated DataFlash log: the record at byte {at} needs {length} bytes, "
                f"{len(data) - at} left"
            )
        if kind == 128:
            lengths[data[at + 3]] = data[at + 4]
        at += length
    return None


def check_log(stack: Stack, data: bytes) -> str | None:
    return check_ulog(data) if stack is Stack.PX4 else check_dataflash(data)


def extension(stack: Stack) -> str:
    return "ulg" if stack is Stack.PX4 else "bin"


# -- the fetcher ----------------------------------------------------------------------

ManifestUpdate = Callable[[Callable[[Manifest], Manifest]], None]


@dataclass
class FetchSettings:
    rate_bytes_per_s: float = DEFAULT_RATE_BYTES_PER_S
    window: int = WINDOW_BYTES
    request_timeout_s: float = REQUEST_TIMEOUT_S
    give_up_s: float = GIVE_UP_S


class AbortedError(Exception):
    """The download stopped (the vehicle armed, the agent stops)."""


class LogFetcher:
    """Downloads the logs of the flight that ended from every autopilot link of ``links()``."""

    def __init__(
        self,
        links: Callable[[], Mapping[str, Any]],
        *,
        settings: FetchSettings | None = None,
        stopping: Callable[[], bool] = lambda: False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._links = links
        self.settings = settings or FetchSettings()
        self._stopping = stopping
        self._clock = clock
        self.bytes_fetched = 0
        self.seconds = 0.0

    def __call__(self, flight_dir: Path, update: ManifestUpdate) -> None:
        for link in list(self._links().values()):
            self._fetch_one(link, flight_dir, update)

    def _armed(self) -> bool:
        for link in self._links().values():
            beat = link.heartbeat()
            if beat is not None and beat[1] & MAV_MODE_FLAG_SAFETY_ARMED:
                return True
        return False

    def _fetch_one(self, link: Any, flight_dir: Path, update: ManifestUpdate) -> None:
        inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        link.log_sink = inbox.put
        try:
            listing = self._list(link, inbox)
            if listing is None:
                log.warning("records: %s did not list its logs", link.name)
                return
            previous = last_fetched(flight_dir.parent, flight_dir.name, link.name)
            chosen = logs_to_fetch(listing, previous)
            if not chosen:
                log.info("records: %s has no log", link.name)
            for log_id, size in chosen:
                self._fetch_log(
                    link, inbox, flight_dir=flight_dir, update=update, log_id=log_id, size=size
                )
        finally:
            link.log_sink = None
            link.send_message("LOG_REQUEST_END")

    def _fetch_log(
        self,
        link: Any,
        inbox: queue.SimpleQueue[Any],
        *,
        flight_dir: Path,
        update: ManifestUpdate,
        log_id: int,
        size: int,
    ) -> None:
        """One log into ``autopilot-logs/<autopilot>/<id>.<ext>``, checked."""
        stack = Stack(link.stack)
        rel = f"{LOGS_DIR}/{link.name}/{log_id}.{extension(stack)}"
        path = flight_dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        entry = FileEntry(rel, FileKind.AUTOPILOT_LOG, autopilot=link.name)
        update(lambda m: m.with_file(entry))
        state, message, have = self._download(
            link, inbox, log_id=log_id, size=size, path=path, entry=entry, update=update
        )
        if state is FileState.COMPLETE:
            data = path.read_bytes()
            problem = check_log(stack, data)
            if problem is not None:
                state, message = FileState.FAILED, problem
        final = replace(
            entry,
            state=state,
            message=message,
            bytes=have,
            sha256=sha256_of(path) if state is FileState.COMPLETE else None,
        )
        update(partial(_with_entry, final))

    def _list(self, link: Any, inbox: queue.SimpleQueue[Any]) -> dict[int, tuple[int, int]] | None:
        for _ in range(3):
            if self._armed():
                raise AbortedError("the vehicle armed")
            link.send_message("LOG_REQUEST_LIST", start=0, end=0xFFFF)
            entries: dict[int, tuple[int, int]] = {}
            deadline = self._clock() + LIST_TIMEOUT_S
            expected: int | None = None
            while self._clock() < deadline:
                msg = _get(inbox, deadline - self._clock())
                if msg is None or msg.get_type() != "LOG_ENTRY":
                    continue
                expected = int(msg.num_logs)
                if expected == 0:
                    return {}
                entries[int(msg.id)] = (int(msg.time_utc), int(msg.size))
                if len(entries) >= expected:
                    return entries
            if entries:
                return entries
        return None

    def _download(
        self,
        link: Any,
        inbox: queue.SimpleQueue[Any],
        *,
        log_id: int,
        size: int,
        path: Path,
        entry: FileEntry,
        update: ManifestUpdate,
    ) -> tuple[FileState, str, int]:
        s = self.settings
        have = Intervals()
        eof: int | None = None  # where the autopilot said the file ends, when before size
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
        started = self._clock()
        progress_at = last_byte = started
        try:
            while True:
                target = size if eof is None else eof
                request = next_request(have, target, s.window)
                if request is None:
                    break
                if self._stopping():
                    return FileState.FAILED, "the agent stopped during the download", have.covered()
                if self._armed():
                    return (
                        FileState.FAILED,
                        f"aborted: the vehicle armed ({have.covered()} of {size} bytes fetched)",
                        have.covered(),
                    )
                now = self._clock()
                if now - last_byte > s.give_up_s:
                    return (
                        FileState.FAILED,
                        f"the autopilot sent nothing for {s.give_up_s:g} s "
                        f"({have.covered()} of {size} bytes fetched)",
                        have.covered(),
                    )
                ofs, count = request
                window_start = now
                link.send_message("LOG_REQUEST_DATA", id=log_id, ofs=ofs, count=count)
                deadline = now + s.request_timeout_s
                got = 0
                while got < count and self._clock() < deadline:
                    msg = _get(inbox, deadline - self._clock())
                    if msg is None or msg.get_type() != "LOG_DATA" or int(msg.id) != log_id:
                        continue
                    n = int(msg.count)
                    at = int(msg.ofs)
                    if n == 0:
                        eof = min(at, eof if eof is not None else at)
                        break
                    os.pwrite(fd, bytes(msg.data)[:n], at)
                    have.add(at, at + n)
                    got += n
                    last_byte = self._clock()
                    if at + n >= ofs + count:
                        break
                self.bytes_fetched += got
                # pacing: this window no faster than the rate allows
                pause = count / s.rate_bytes_per_s - (self._clock() - window_start)
                if pause > 0:
                    time.sleep(pause)
                if self._clock() - progress_at > PROGRESS_EVERY_S:
                    progress_at = self._clock()
                    update(partial(_with_entry, replace(entry, bytes=have.covered())))
            os.fsync(fd)
        except OSError as exc:  # this log fails; the next autopilot's is still tried
            why = "the disk is full" if exc.errno == errno.ENOSPC else f"cannot write: {exc}"
            return (
                FileState.FAILED,
                f"{why} ({have.covered()} of {size} bytes fetched)",
                have.covered(),
            )
        finally:
            os.close(fd)
            self.seconds += self._clock() - started
        if eof is not None and eof < size:
            return (
                FileState.FAILED,
                f"truncated: the autopilot's file ends at byte {eof}, its listing says {size}",
                have.covered(),
            )
        return FileState.COMPLETE, "", have.covered()


def _with_entry(entry: FileEntry, manifest: Manifest) -> Manifest:
    return manifest.with_file(entry)


def _get(inbox: queue.SimpleQueue[Any], timeout: float) -> Any:
    if timeout <= 0:
        return None
    try:
        return inbox.get(timeout=timeout)
    except queue.Empty:
        return None
