"""A vehicle's flight records server as the records contract specifies it, serving a
real directory over real HTTP on the loopback — for the operator's gathering tests.

It is the contract's server (``GET /records``, ``/records/<flightId>/<path>`` with
``Range: bytes=N-`` → 206, JSON 404s, paths outside a flight refused), written here so
the operator's side is tested over a real socket; the agent's own server is tested on
its side. Two faults a WiFi link produces are built in: :meth:`RecordServer.cut_next`
ends the next transfer of a file after N bytes (the connection drops mid-body), and
:meth:`RecordServer.stop` / :meth:`RecordServer.start` take the vehicle away and bring
it back on the same port. :func:`write_flight` lays out a flight directory with its
``flight.json`` and sha256s, optionally a wrong one (a file corrupted on the vehicle).
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections.abc import Mapping
from datetime import datetime
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import unquote, urlsplit

from roost_localcluster.controlplane import free_port


def iso(moment: datetime | None) -> str | None:
    return moment.isoformat().replace("+00:00", "Z") if moment is not None else None


def write_flight(
    directory: Path,
    vehicle: str,
    armed_at: datetime,
    files: Mapping[str, bytes],
    *,
    disarmed_at: datetime | None = None,
    state: str = "Recording",
    corrupt: frozenset[str] = frozenset(),
) -> str:
    """A flight directory as the agent leaves it; returns its flightId. ``corrupt``:
    paths whose listed sha256 is not their content's."""
    flight_id = f"{vehicle}-{armed_at:%Y%m%dT%H%M%SZ}"
    root = directory / flight_id
    entries = []
    for path, data in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(data)
        digest = hashlib.sha256(data + (b"x" if path in corrupt else b"")).hexdigest()
        kind = (
            "tlog" if path.endswith(".tlog") else "decisions" if "decisions" in path else "params"
        )
        entries.append(
            {"path": path, "bytes": len(data), "sha256": digest, "kind": kind, "state": "Complete"}
        )
    manifest = {
        "flightId": flight_id,
        "vehicle": vehicle,
        "armedAt": iso(armed_at),
        "disarmedAt": iso(disarmed_at),
        "state": state,
        "message": None,
        "files": entries,
        "dropped": {"tlog": 0, "decisions": 0},
    }
    (root / "flight.json").write_text(json.dumps(manifest))
    return flight_id


def land(directory: Path, flight_id: str, at: datetime) -> None:
    """The flight ends: disarmed at ``at``, Complete."""
    path = directory / flight_id / "flight.json"
    manifest = json.loads(path.read_text())
    manifest.update(disarmedAt=iso(at), state="Complete")
    path.write_text(json.dumps(manifest))


class RecordServer:
    """The contract's records server over ``directory`` on a fixed loopback port."""

    def __init__(self, directory: Path, vehicle: str) -> None:
        self.directory = directory
        self.vehicle = vehicle
        self.port = free_port()
        self.cuts: dict[str, int] = {}
        self.requests: list[tuple[str, str | None]] = []
        self._server: ThreadingHTTPServer | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def cut_next(self, route: str, after_bytes: int) -> None:
        """The next GET of ``route`` (``records/<id>/<path>``) stops after that many bytes."""
        self.cuts[route] = after_bytes

    def start(self) -> RecordServer:
        server = ThreadingHTTPServer(("127.0.0.1", self.port), self._handler())
        server.daemon_threads = True
        threading.Thread(target=server.serve_forever, daemon=True).start()
        self._server = server
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None

    def listing(self) -> dict[str, Any]:
        flights = [json.loads(p.read_text()) for p in sorted(self.directory.glob("*/flight.json"))]
        flights.sort(key=lambda f: f["armedAt"], reverse=True)
        return {"vehicle": self.vehicle, "flights": flights}

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: Any) -> None:
                return

            def _json(self, status: int, value: Any) -> None:
                body = json.dumps(value).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self) -> None:
                route = unquote(urlsplit(self.path).path).strip("/")
                owner.requests.append((route, self.headers.get("Range")))
                if route == "records":
                    self._json(HTTPStatus.OK, owner.listing())
                    return
                parts = PurePosixPath(route).parts
                path = owner.directory.joinpath(*parts[1:]) if len(parts) >= 3 else None
                if path is None or parts[0] != "records" or ".." in parts or not path.is_file():
                    self._json(HTTPStatus.NOT_FOUND, {"error": f"unknown: {route}"})
                    return
                data = path.read_bytes()
                offset = 0
                header = self.headers.get("Range") or ""
                if header.startswith("bytes=") and header.endswith("-"):
                    offset = int(header[6:-1])
                self.send_response(HTTPStatus.PARTIAL_CONTENT if offset else HTTPStatus.OK)
                self.send_header("Content-Length", str(len(data) - offset))
                self.end_headers()
                cut = owner.cuts.pop(route, None)
                if cut is not None:
                    self.wfile.write(data[offset : offset + cut])
                    self.wfile.flush()
                    self.close_connection = True
                    return
                self.wfile.write(data[offset:])

        return Handler
