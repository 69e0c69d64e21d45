"""The vehicle's flight records over HTTP (``--records-port``, default 9468).

The operator gathers a Mission's records through the API server's pod proxy, over a
WiFi link that drops: so every file is served with ``Range: bytes=N-`` (206), and a cut
transfer resumes where it stopped instead of starting again. Only the files of a flight
directory are served (:func:`roost_agent.records.resolve_record` refuses anything that
leaves it); anything unknown is a 404 with a JSON ``{"error": ...}``.

- ``GET /records``: ``{"vehicle", "flights": [manifest, ...]}``, newest first;
- ``GET /records/<flightId>/flight.json``: that flight's manifest;
- ``GET /records/<flightId>/<path>``: the file's bytes.

Standard library only (``http.server``, one thread per request): the agent's resident
memory stays small, and a transfer never runs on a thread that flies.
"""

from __future__ import annotations

import json
import logging
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from roost_agent.records import (
    RangeNotSatisfiableError,
    parse_range,
    read_manifests,
    resolve_record,
)

log = logging.getLogger(__name__)

CHUNK = 1 << 16


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("records: " + format, *args)

    def do_GET(self) -> None:
        self._answer(body=True)

    def do_HEAD(self) -> None:
        self._answer(body=False)

    def _answer(self, *, body: bool) -> None:
        path = unquote(urlsplit(self.path).path)
        root = self.server.root
        if path.rstrip("/") == "/records":
            flights = [m.to_json() for m in read_manifests(root)]
            self._json(HTTPStatus.OK, {"vehicle": self.server.vehicle, "flights": flights}, body)
            return
        prefix = "/records/"
        if not path.startswith(prefix):
            self._json(HTTPStatus.NOT_FOUND, {"error": f"no such resource: {path}"}, body)
            return
        flight, _, rest = path[len(prefix) :].partition("/")
        target = resolve_record(root, flight, rest)
        if target is None:
            self._json(HTTPStatus.NOT_FOUND, {"error": f"no such record: {path}"}, body)
            return
        self._file(target, body)

    def _json(self, status: HTTPStatus, doc: dict[str, Any], body: bool) -> None:
        data = json.dumps(doc).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _file(self, target: Path, body: bool) -> None:
        try:
            data = target.open("rb")  # closed below, after streaming
        except OSError:
            self._json(HTTPStatus.NOT_FOUND, {"error": f"no such record: {target.name}"}, body)
            return
        with data:
            size = data.seek(0, 2)
            try:
                wanted = parse_range(self.headers.get("Range"), size)
            except RangeNotSatisfiableError:
                self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                self.send_header("Content-Range", f"bytes */{size}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            start, length = (0, size) if wanted is None else (wanted.start, wanted.length)
            self.send_response(HTTPStatus.OK if wanted is None else HTTPStatus.PARTIAL_CONTENT)
            content = "application/json" if target.suffix in (".json", ".jsonl") else None
            self.send_header("Content-Type", content or "application/octet-stream")
            self.send_header("Accept-Ranges", "bytes")
            self.send_header("Content-Length", str(length))
            if wanted is not None:
                self.send_header("Content-Range", f"bytes {start}-{wanted.end}/{size}")
            self.end_headers()
            if not body:
                return
            data.seek(start)
            try:
                _copy(data, self.wfile, length)
            except (BrokenPipeError, ConnectionResetError):
                log.debug("records: %s: the client went away", target)


def _copy(source: Any, sink: Any, length: int) -> None:
    """``length`` bytes (a file still being written may be longer now: only what the
    headers announced is sent)."""
    left = length
    while left > 0:
        chunk = source.read(min(CHUNK, left))
        if not chunk:
            break
        sink.write(chunk)
        left -= len(chunk)
    if left:  # the file shrank meanwhile (deleted by the budget): end the connection
        raise ConnectionResetError


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], root: Path, vehicle: str) -> None:
        self.root = root
        self.vehicle = vehicle
        super().__init__(address, _Handler)


class RecordsServer:
    """Serves the records under ``root`` on ``address:port`` (0: a free port)."""

    def __init__(self, root: Path, vehicle: str, *, address: str = "127.0.0.1", port: int = 0):
        self._server = _Server((address, port), root, vehicle)
        self.address = address
        self.port = int(self._server.server_address[1])
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="records-http", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.address}:{self.port}/records"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2)
