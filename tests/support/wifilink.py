"""A vehicle's WiFi link for records tests: a TCP relay on the loopback in front of the
agent's records server, that can drop.

The agent's real :class:`~roost_agent.records_server.RecordsServer` serves the flights;
the operator talks to it through this relay, which forwards bytes both ways and adds
the two faults a WiFi link produces: :meth:`WifiLink.cut_after` drops the first
connection over which the server sends more than N bytes, right there (a transfer cut
mid-file; listings are far smaller than a tlog),
and :meth:`WifiLink.down` / :meth:`WifiLink.up` take the vehicle out of range and bring
it back on the same port. :func:`write_flight` and :func:`land` lay out flight
directories with the agent's own manifest code, as its recorder leaves them.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Mapping
from dataclasses import replace
from datetime import datetime
from pathlib import Path

from roost_agent.records import FileEntry, Manifest, read_manifest, write_manifest
from roost_api.ports import free_port
from roost_api.records import FileKind, FileState, FlightState, sha256_of

KINDS = {".tlog": FileKind.TLOG, ".jsonl": FileKind.DECISIONS, ".json": FileKind.PARAMS}


def write_flight(
    root: Path,
    vehicle: str,
    armed_at: datetime,
    files: Mapping[str, bytes],
    *,
    disarmed_at: datetime | None = None,
    state: FlightState = FlightState.RECORDING,
    corrupt: frozenset[str] = frozenset(),
) -> str:
    """A flight directory under ``root``; returns its flightId. ``corrupt``: paths whose
    bytes change after their sha256 was listed (a card that corrupted them)."""
    flight_id = f"{vehicle}-{armed_at:%Y%m%dT%H%M%SZ}"
    manifest = Manifest(flight_id, vehicle, armed_at, disarmed_at, state)
    for path, data in files.items():
        target = root / flight_id / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
        kind = KINDS.get(target.suffix, FileKind.AUTOPILOT_LOG)
        entry = FileEntry(path, kind, FileState.COMPLETE, len(data), sha256_of(target))
        manifest = manifest.with_file(entry)
        if path in corrupt:
            target.write_bytes(data[::-1] + b"!")
    write_manifest(root, manifest)
    return flight_id


def land(root: Path, flight_id: str, at: datetime) -> None:
    """The flight ends: disarmed at ``at``, its files written: Complete."""
    manifest = read_manifest(root, flight_id)
    assert manifest is not None, flight_id
    write_manifest(root, replace(manifest, disarmed_at=at, state=FlightState.COMPLETE))


class WifiLink:
    """A relay from a fixed loopback port to ``target_port`` (see the module docstring)."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.port = free_port()
        self._cut: int | None = None
        self._lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._open: set[socket.socket] = set()
        self.cuts = 0
        self._refuse_in: int | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def cut_after(self, after_bytes: int) -> None:
        """Drop the first connection whose server sends more than ``after_bytes`` bytes."""
        self._cut = after_bytes

    def drop_connection(self, nth: int) -> None:
        """Drop the ``nth`` connection from now as soon as it is accepted, before anything
        is relayed (a link lost between two requests of a client that opens one
        connection per request); the ones before it go through."""
        self._refuse_in = nth

    def up(self) -> WifiLink:
        listener = socket.create_server(("127.0.0.1", self.port))
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()
        return self

    def down(self) -> None:
        """Out of range: nothing listens, open connections drop."""
        if self._listener is not None:
            with contextlib.suppress(OSError):  # wakes the thread blocked in accept()
                self._listener.shutdown(socket.SHUT_RDWR)
            self._listener.close()
            self._listener = None
        with self._lock:
            for sock in self._open:
                sock.close()
            self._open.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            if self._dropped_now():
                client.close()
                continue
            try:
                server = socket.create_connection(self.target, timeout=10)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._open.update((client, server))
            threading.Thread(target=self._pump, args=(client, server, False), daemon=True).start()
            threading.Thread(target=self._pump, args=(server, client, True), daemon=True).start()

    def _dropped_now(self) -> bool:
        with self._lock:
            if self._refuse_in is None:
                return False
            self._refuse_in -= 1
            if self._refuse_in > 0:
                return False
            self._refuse_in = None
            self.cuts += 1
            return True

    def _take_cut(self, sent: int) -> int | None:
        """Where to cut a connection that has sent ``sent`` bytes and more coming (once)."""
        with self._lock:
            cut = self._cut
            if cut is None:
                return None
            self._cut = None
            self.cuts += 1
            return max(cut - sent, 0)

    def _pump(self, source: socket.socket, sink: socket.socket, answers: bool) -> None:
        sent = 0
        try:
            while data := source.recv(1 << 16):
                cut = self._cut
                if answers and cut is not None and sent + len(data) > cut:
                    keep = self._take_cut(sent)
                    if keep is not None:
                        sink.sendall(data[:keep])
                        break
                sink.sendall(data)
                sent += len(data)
        except OSError:
            pass
        finally:
            for sock in (source, sink):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
            with self._lock:
                self._open.discard(source)
                self._open.discard(sink)
