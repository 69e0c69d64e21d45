"""The flight recorder: every flight's MAVLink traffic, decisions and parameters on disk.

Off the hot path. Each autopilot link calls :class:`FrameTap` with every frame it
accepted (after the hub routed it) and every frame it wrote (after the write); the tap
appends ``(wall time, bytes)`` to a bounded queue and returns. When the queue is full
the frame is dropped and counted (``dropped.tlog`` in the manifest, and the metric
``roost_agent_records_dropped_total``): a recorder that cannot keep up must never slow
the routing or the failover. One writer thread drains the queue every
:data:`WRITE_PERIOD_S`, writes, and ``fsync``\\s at least every :data:`SYNC_PERIOD_S`:
a power cut loses at most about the last second.

A flight is the vehicle's armed interval: it starts when any autopilot's fresh
heartbeat says armed and ends when every autopilot heard recently says disarmed
(:func:`in_flight`). The last :data:`PREROLL_S` seconds before arming are written first,
so the arming command and its answer are in the record.

- ``hub.tlog``: the frames, each after an 8-byte big-endian microsecond UNIX time, the
  format of MAVProxy's and QGroundControl's telemetry logs (pymavlink reads it). Every
  autopilot's frames keep their own system id, and clients' frames appear as the
  autopilot they were routed to received them.
- ``decisions.jsonl``: the agent's events (:meth:`roost_agent.agent.Agent.subscribe`,
  the same path the Kubernetes Events and the stdout lines come from).
- ``params/<autopilot>.json``: the parameters each autopilot had at arming, from the
  PARAM_VALUEs seen on its link (the full list is asked for once per boot while
  disarmed).

The disk budget (:func:`roost_agent.records.choose_deletions`) deletes the oldest
flights, never the current one (on the ground, never the last one); when the current
flight alone is over budget, or the disk is full, that flight is marked Failed with a
message and recording stops for it. Flying goes on either way. After landing the
autopilots' logs are fetched (:mod:`roost_agent.records_logs`).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import IO, Any, Protocol

from roost_agent.records import (
    DECISIONS,
    DEFAULT_KEEP_FREE_PERCENT,
    LOGS_DIR,
    PARAMS_DIR,
    TLOG,
    FileEntry,
    Manifest,
    budget_within_disk,
    choose_deletions,
    delete_flight,
    flight_id,
    fsync_directory,
    read_manifest,
    read_manifests,
    stored_flights,
    write_manifest,
)
from roost_api.records import FileKind, FileState, FlightState, sha256_of
from roost_mavlink import MAV_MODE_FLAG_SAFETY_ARMED
from roost_mavlink.codec import V1_MAGIC, V2_MAGIC, Frame, scan

log = logging.getLogger(__name__)

QUEUE_FRAMES = 50_000  # ~5 s of a busy vehicle's traffic, ~10 MB at most
DECISION_QUEUE = 10_000
WRITE_PERIOD_S = 0.2
SYNC_PERIOD_S = 0.8
PREROLL_S = 3.0
STALE_S = 3.0  # an autopilot not heard this long does not count for armed/disarmed
BUDGET_CHECK_S = 5.0
PARAM_VALUE_ID = 22
_STAMP = struct.Struct(">Q")


class FrameTap:
    """The hot path's part: ``tap(frame)`` appends it with the time, or counts a drop.

    ``deque.append`` and ``popleft`` are atomic, so producers (the link reader, the
    hub's thread, the agent's senders) and the writer need no lock."""

    __slots__ = ("_items", "capacity", "dropped")

    def __init__(self, capacity: int = QUEUE_FRAMES) -> None:
        self._items: deque[tuple[float, bytes]] = deque()
        self.capacity = capacity
        self.dropped = 0

    def __call__(self, frame: bytes) -> None:
        items = self._items
        if len(items) < self.capacity:
            items.append((time.time(), frame))
        else:
            self.dropped += 1

    def drain(self) -> list[tuple[float, bytes]]:
        items = self._items
        pop = items.popleft
        return [pop() for _ in range(len(items))]


def tlog_record(at: float, frame: bytes) -> bytes:
    """One tlog entry: the microsecond UNIX time, big-endian, then the raw frame."""
    return _STAMP.pack(int(at * 1_000_000)) + frame


def in_flight(flying: bool, beats: Iterable[tuple[bool, float] | None], now: float) -> bool:
    """Whether the vehicle is in flight, from each autopilot's last heartbeat
    ``(armed, received at)``: a flight starts with any fresh armed heartbeat and ends
    when every fresh one says disarmed; with none fresh (every link silent) nothing is
    known and the state stays."""
    fresh = [armed for armed, at in (b for b in beats if b is not None) if now - at <= STALE_S]
    if not fresh:
        return flying
    return any(fresh)


def frame_source(frame: bytes) -> tuple[int, int] | None:
    """(system id, message id) of a raw frame."""
    if len(frame) < 8:
        return None
    if frame[0] == V2_MAGIC and len(frame) >= 10:
        return frame[5], frame[7] | frame[8] << 8 | frame[9] << 16
    if frame[0] == V1_MAGIC:
        return frame[3], frame[5]
    return None


class RecordedLink(Protocol):
    name: str
    stack: Any
    spec: Any
    record: Callable[[bytes], None] | None

    def heartbeat(self) -> tuple[int, int, float] | None: ...

    def send_message(self, name: str, **values: Any) -> bool: ...


class RecordedAgent(Protocol):
    @property
    def vehicle_name(self) -> str: ...

    @property
    def links(self) -> Mapping[str, Any]: ...

    def subscribe(self, listener: Callable[[Any], None]) -> Callable[[], None]: ...


@dataclass
class _ParamTable:
    count: int = 0
    values: dict[str, float] = field(default_factory=dict)
    asked_at: float | None = None
    heartbeat_at: float | None = None


@dataclass
class _Flight:
    manifest: Manifest
    tlog: IO[bytes] | None
    decisions: IO[bytes] | None
    written: int = 0  # bytes written by the recorder to this flight
    failed: bool = False
    tap_base: int = 0  # the tap's drops before this flight
    decisions_base: int = 0
    lost_frames: int = 0  # not written: recording had stopped (disk full, budget)
    lost_lines: int = 0


class FlightRecorder:
    """Records the agent's flights under ``root`` within ``budget_bytes``.

    ``fetch_logs(flight_dir, manifest_update)`` runs after landing on its own thread
    (the autopilot log fetcher); None: logs are not fetched."""

    def __init__(
        self,
        agent: RecordedAgent,
        root: Path,
        *,
        budget_bytes: int,
        fetch_logs: Callable[[Path, Callable[[Callable[[Manifest], Manifest]], None]], None]
        | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], datetime] = lambda: datetime.now(UTC),
        queue_frames: int = QUEUE_FRAMES,
        budget_check_s: float = BUDGET_CHECK_S,
        keep_free: float = DEFAULT_KEEP_FREE_PERCENT / 100,
    ) -> None:
        self._agent = agent
        self.root = root
        self.budget_bytes = budget_bytes
        self.keep_free = keep_free
        self._fetch_logs = fetch_logs
        self._clock = clock
        self._wall_clock = wall_clock
        self.tap = FrameTap(queue_frames)
        self._budget_check_s = budget_check_s
        self._decisions: deque[bytes] = deque()
        self.decisions_dropped = 0
        self._preroll: deque[tuple[float, bytes]] = deque()
        self._preroll_decisions: deque[tuple[float, bytes]] = deque()
        self._params: dict[int, _ParamTable] = {}
        self._flight: _Flight | None = None
        self._manifest_lock = threading.Lock()
        self._step_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._fetcher: threading.Thread | None = None
        self._last_sync = 0.0
        self._last_budget = 0.0
        self.flights_recorded = 0
        self.frames_written = 0
        self.cpu_s = 0.0  # CPU time of the recording rounds (the writer's side)
        # Paused: the links are detached (nothing is tapped); the benchmark compares.
        self.paused = False
        root.mkdir(parents=True, exist_ok=True)
        close_interrupted(root)

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        self._attach()
        self._unsubscribe = self._agent.subscribe(self._on_event)
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop recording; a flight in the air is closed as it stands, Failed: the
        agent stopped, not the vehicle."""
        self._stop.set()
        if self._unsubscribe is not None:
            self._unsubscribe()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for link in self._agent.links.values():
            if link.record is self.tap:
                link.record = None
        flight = self._flight
        if flight is not None:  # closed as it stands, and says why
            self._close_files(flight)
            name = flight.manifest.flight_id
            files = tuple(self._finished(name, f) for f in flight.manifest.files)
            flight.manifest = replace(
                flight.manifest, files=files, dropped=self._dropped(flight)
            ).failed("the agent was stopped during the flight")
            try:
                self._save(flight)
            except OSError:
                log.exception("records: cannot write the manifest of %s", name)
        fetcher = self._fetcher
        if fetcher is not None:
            fetcher.join(timeout=5)

    @property
    def current(self) -> str | None:
        flight = self._flight
        return None if flight is None else flight.manifest.flight_id

    @property
    def dropped_frames(self) -> int:
        """Frames the tap dropped (queue full) since the agent started."""
        return self.tap.dropped

    # -- inputs --------------------------------------------------------------------------

    def _attach(self) -> None:
        """Every link of the agent records into the tap (a link replaced by a spec
        change is attached on the next round); none while paused."""
        wanted = None if self.paused else self.tap
        for link in self._agent.links.values():
            if link.record is not wanted:
                link.record = wanted

    def _on_event(self, event: Any) -> None:
        """The agent's event path (its notifier thread): one JSON line, queued."""
        if len(self._decisions) >= DECISION_QUEUE:
            self.decisions_dropped += 1
            return
        line = json.dumps(event.to_json(), default=str).encode() + b"\n"
        self._decisions.append(line)

    # -- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.wait(WRITE_PERIOD_S):
            try:
                self.step()
            except Exception:  # the recorder outlives any bug in one round
                log.exception("records: a recording round failed")

    def step(self) -> None:
        """One round: attach links, follow arming, write what was queued, keep the
        budget (also called by the benchmark to attach or detach at once)."""
        with self._step_lock:
            started = time.thread_time()
            self._step()
            self.cpu_s += time.thread_time() - started

    def _step(self) -> None:
        now = self._clock()
        self._attach()
        frames = self.tap.drain()
        lines = [self._decisions.popleft() for _ in range(len(self._decisions))]
        self._watch_params(frames, now)
        flying = self._flight is not None
        beats = [self._armed_beat(link) for link in self._agent.links.values()]
        airborne = in_flight(flying, beats, now)
        if airborne and not flying:
            self._begin(now)
        flight = self._flight
        if flight is None:
            self._keep_preroll(frames, lines)
        else:
            self._write(flight, frames, lines, now)
        if flight is not None and not airborne:
            self._end(flight)
        if now - self._last_budget >= self._budget_check_s:
            self._last_budget = now
            self._keep_budget()

    @staticmethod
    def _armed_beat(link: Any) -> tuple[bool, float] | None:
        beat = link.heartbeat()
        if beat is None:
            return None
        return bool(beat[1] & MAV_MODE_FLAG_SAFETY_ARMED), beat[2]

    def _keep_preroll(self, frames: list[tuple[float, bytes]], lines: list[bytes]) -> None:
        now = time.time()
        self._preroll.extend(frames)
        self._preroll_decisions.extend((now, line) for line in lines)
        for ring in (self._preroll, self._preroll_decisions):
            while ring and ring[0][0] < now - PREROLL_S:
                ring.popleft()

    # -- parameters ----------------------------------------------------------------------

    def _watch_params(self, frames: list[tuple[float, bytes]], now: float) -> None:
        # one comprehension over every frame (no call per frame): PARAM_VALUEs are few
        found = [
            f
            for _, f in frames
            if len(f) > 9
            and (
                (f[0] == V2_MAGIC and f[7] == PARAM_VALUE_ID and not f[8] and not f[9])
                or (f[0] == V1_MAGIC and f[5] == PARAM_VALUE_ID)
            )
        ]
        for frame in found:
            source = frame_source(frame)
            if source is None or source[1] != PARAM_VALUE_ID:
                continue
            items, _ = scan(frame)
            for msg in items:
                if not isinstance(msg, Frame) or msg.get_type() != "PARAM_VALUE":
                    continue
                table = self._params.setdefault(source[0], _ParamTable())
                name = bytes(msg.param_id).split(b"\0", 1)[0].decode("ascii", "replace")
                table.values[name] = float(msg.param_value)
                table.count = int(msg.param_count)
        if self._flight is not None:
            return
        for link in self._agent.links.values():  # the full list, once per boot, disarmed
            beat = link.heartbeat()
            if beat is None or beat[1] & MAV_MODE_FLAG_SAFETY_ARMED:
                continue
            table = self._params.setdefault(int(link.spec.sysid), _ParamTable())
            rebooted = table.heartbeat_at is not None and beat[2] - table.heartbeat_at > STALE_S
            table.heartbeat_at = beat[2]
            if rebooted:
                table.asked_at = None
            if table.asked_at is None or (
                len(table.values) < table.count and now - table.asked_at > 30.0
            ):
                table.asked_at = now
                link.send_message("PARAM_REQUEST_LIST")

    def _write_params(self, flight: _Flight) -> None:
        directory = self.root / flight.manifest.flight_id / PARAMS_DIR
        directory.mkdir(exist_ok=True)
        for link in self._agent.links.values():
            table = self._params.get(int(link.spec.sysid), _ParamTable())
            doc = {
                "autopilot": link.name,
                "sysid": int(link.spec.sysid),
                "stack": str(getattr(link.stack, "value", link.stack)),
                "count": table.count,
                "complete": table.count > 0 and len(table.values) >= table.count,
                "params": dict(sorted(table.values.items())),
            }
            path = f"{PARAMS_DIR}/{link.name}.json"
            data = json.dumps(doc, indent=1).encode()
            (self.root / flight.manifest.flight_id / path).write_bytes(data)
            message = (
                ""
                if doc["complete"]
                else (
                    f"{len(table.values)} of {table.count or 'unknown'} parameters known at arming"
                )
            )
            entry = FileEntry(
                path,
                FileKind.PARAMS,
                FileState.COMPLETE,
                len(data),
                sha256_of(self.root / flight.manifest.flight_id / path),
                autopilot=link.name,
                message=message,
            )
            flight.manifest = flight.manifest.with_file(entry)
            flight.written += len(data)

    # -- a flight ------------------------------------------------------------------------

    def _begin(self, now: float) -> None:
        armed_at = self._wall_clock()
        existing = [p.name for p in self.root.iterdir()]
        name = flight_id(self._agent.vehicle_name, armed_at, existing)
        manifest = Manifest(name, self._agent.vehicle_name, armed_at)
        flight = _Flight(
            manifest, None, None, tap_base=self.tap.dropped, decisions_base=self.decisions_dropped
        )
        self._flight = flight
        self.flights_recorded += 1
        log.info("records: flight %s began", name)
        try:
            directory = self.root / name
            directory.mkdir()
            flight.tlog = (directory / TLOG).open("ab")  # closed when the flight ends
            flight.decisions = (directory / DECISIONS).open("ab")
            flight.manifest = manifest.with_file(FileEntry(TLOG, FileKind.TLOG)).with_file(
                FileEntry(DECISIONS, FileKind.DECISIONS)
            )
            self._write_params(flight)
            self._save(flight)
            fsync_directory(self.root)
        except OSError as exc:
            self._fail(flight, exc)
        preroll, self._preroll = list(self._preroll), deque()
        lines = [line for _, line in self._preroll_decisions]
        self._preroll_decisions.clear()
        self._write(flight, preroll, lines, now)
        self._keep_budget()

    def _write(
        self, flight: _Flight, frames: list[tuple[float, bytes]], lines: list[bytes], now: float
    ) -> None:
        if flight.failed or flight.tlog is None or flight.decisions is None:
            flight.lost_frames += len(frames)
            flight.lost_lines += len(lines)
            return
        try:
            data = b"".join([_STAMP.pack(int(at * 1_000_000)) + frame for at, frame in frames])
            flight.tlog.write(data)
            self.frames_written += len(frames)
            flight.decisions.write(b"".join(lines))
            flight.written += len(data) + sum(len(line) for line in lines)
            if now - self._last_sync >= SYNC_PERIOD_S:
                self._last_sync = now
                for out in (flight.tlog, flight.decisions):
                    out.flush()
                    os.fsync(out.fileno())
                self._sync_manifest(flight)
        except OSError as exc:
            self._fail(flight, exc)

    def _sync_manifest(self, flight: _Flight) -> None:
        manifest = flight.manifest
        for path in (TLOG, DECISIONS):
            entry = manifest.file(path)
            if entry is not None:
                size = _size(self.root / manifest.flight_id / path)
                manifest = manifest.with_file(replace(entry, bytes=size))
        flight.manifest = replace(manifest, dropped=self._dropped(flight))
        self._save(flight)

    def _dropped(self, flight: _Flight) -> dict[str, int]:
        return {
            "tlog": self.tap.dropped - flight.tap_base + flight.lost_frames,
            "decisions": self.decisions_dropped - flight.decisions_base + flight.lost_lines,
        }

    def _save(self, flight: _Flight) -> None:
        with self._manifest_lock:
            write_manifest(self.root, flight.manifest)

    def _fail(self, flight: _Flight, exc: OSError) -> None:
        """Recording this flight stops; flying does not."""
        if exc.errno == errno.ENOSPC:
            message = f"the disk is full ({exc}): recording stopped"
        else:
            message = f"cannot write the record: {exc}"
        self._give_up(flight, message)

    def _give_up(self, flight: _Flight, message: str) -> None:
        if flight.failed:
            return
        log.error("records: flight %s: %s", flight.manifest.flight_id, message)
        flight.failed = True
        self._close_files(flight)
        files = tuple(
            replace(f, state=FileState.FAILED, message=message)
            if f.state is FileState.PARTIAL
            else f
            for f in flight.manifest.files
        )
        flight.manifest = replace(flight.manifest, files=files).failed(message)
        try:
            self._save(flight)
        except OSError:
            log.exception(
                "records: cannot even write the manifest of %s", flight.manifest.flight_id
            )

    @staticmethod
    def _close_files(flight: _Flight) -> None:
        for out in (flight.tlog, flight.decisions):
            if out is None:
                continue
            try:
                out.close()  # flushes
            except OSError:
                log.debug("records: closing a file failed", exc_info=True)
        flight.tlog = flight.decisions = None

    def _end(self, flight: _Flight) -> None:
        self._flight = None
        name = flight.manifest.flight_id
        log.info("records: flight %s ended", name)
        if not flight.failed:
            try:
                for out in (flight.tlog, flight.decisions):
                    if out is not None:
                        out.flush()
                        os.fsync(out.fileno())
            except OSError as exc:
                self._fail(flight, exc)
        self._close_files(flight)
        manifest = replace(
            flight.manifest,
            disarmed_at=self._wall_clock(),
            files=tuple(self._finished(name, f) for f in flight.manifest.files),
            dropped=self._dropped(flight),
        )
        if manifest.state is FlightState.RECORDING:
            manifest = replace(manifest, state=FlightState.LANDED)
        flight.manifest = manifest
        try:
            self._save(flight)
        except OSError:
            log.exception("records: cannot write the manifest of %s", name)
            return
        if self._fetch_logs is None or flight.failed:
            self._update(name, Manifest.settled)
            return
        directory = self.root / name
        (directory / LOGS_DIR).mkdir(exist_ok=True)
        fetch = self._fetch_logs

        def run() -> None:
            try:
                fetch(directory, lambda change: self._update(name, change))
            except Exception as exc:  # a failed fetch marks the flight, never the agent
                log.exception("records: fetching the autopilots' logs failed")
                self._update(name, partial(_fetch_failed, f"fetching the autopilots' logs: {exc}"))
                return
            self._update(name, Manifest.settled)

        self._fetcher = threading.Thread(target=run, name="autopilot-logs", daemon=True)
        self._fetcher.start()

    def _finished(self, flight: str, entry: FileEntry) -> FileEntry:
        return finished_entry(self.root, flight, entry)

    def _update(self, flight: str, change: Callable[[Manifest], Manifest]) -> None:
        """Change a landed flight's manifest (the log fetcher's thread)."""
        with self._manifest_lock:
            manifest = read_manifest(self.root, flight)
            if manifest is None:
                return  # deleted by the budget meanwhile
            write_manifest(self.root, change(manifest))

    # -- the disk budget -----------------------------------------------------------------

    def _keep_budget(self) -> None:
        try:
            flights = stored_flights(self.root)
            # never the current flight; on the ground never the last one either (a
            # flight too big for the budget alone keeps its record of why it failed)
            last = max(flights, key=lambda f: (f.armed_at, f.flight_id), default=None)
            keep = self.current or (last.flight_id if last is not None else None)
            disk = shutil.disk_usage(self.root)
            budget, by_disk = budget_within_disk(
                self.budget_bytes,
                sum(f.bytes for f in flights),
                disk.free,
                disk.total,
                self.keep_free,
            )
            choice = choose_deletions(flights, keep, budget)
        except OSError:
            log.exception("records: cannot measure the records")
            return
        for name in choice.delete:
            log.info("records: deleting flight %s (disk budget)", name)
            delete_flight(self.root, name)
        flight = self._flight
        if not choice.fits and flight is not None:
            self._give_up(
                flight,
                (
                    f"the disk is nearly full: it keeps {self.keep_free * 100:g}% free for "
                    "the node (the kubelet evicts pods below 10%), and this flight alone "
                    "reaches that: recording stopped"
                )
                if by_disk
                else f"the disk budget of {self.budget_bytes / 1e6:g} MB is reached by this "
                "flight alone: recording stopped",
            )


def finished_entry(root: Path, flight: str, entry: FileEntry) -> FileEntry:
    """A Partial file whose writing is over: its final size and digest."""
    if entry.state is not FileState.PARTIAL or entry.kind is FileKind.AUTOPILOT_LOG:
        return entry
    path = root / flight / entry.path
    try:
        return replace(entry, state=FileState.COMPLETE, bytes=_size(path), sha256=sha256_of(path))
    except OSError as exc:
        return replace(entry, state=FileState.FAILED, message=str(exc))


def close_interrupted(root: Path) -> None:
    """A flight left Recording or Landed by a crash, a power cut or a restart is closed
    as it stands (a cut download is not resumed: the autopilot may have flown since)."""
    for manifest in read_manifests(root):
        if manifest.state is FlightState.RECORDING:
            files = tuple(finished_entry(root, manifest.flight_id, f) for f in manifest.files)
            why = "the agent stopped during the flight (crash or power cut)"
            write_manifest(root, replace(manifest, files=files).failed(why))
        elif manifest.state is FlightState.LANDED:
            why = "the agent stopped during the download of the autopilots' logs"
            write_manifest(root, _fetch_failed(why, manifest))


def _fetch_failed(why: str, manifest: Manifest) -> Manifest:
    files = tuple(
        replace(f, state=FileState.FAILED, message=why) if f.state is FileState.PARTIAL else f
        for f in manifest.files
    )
    return replace(manifest, files=files).failed(why)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
