"""Read-only HTTP over the bundles on the records volume, for the CLI and the dashboard.

``GET /bundles`` → ``{"bundles": [manifest summary, ...]}`` newest first;
``GET /bundles/<bundle>/<path>`` → the file's bytes (``Range: bytes=N-`` → 206, so a
cut download resumes); 404 with ``{"error": ...}`` for anything unknown, and for any
path outside the bundle or a ``.part`` still being written. Nothing is ever written
through it. In a cluster it is reached through the API server's pod proxy of the
operator pod (``get pods/proxy`` in the operator's namespace decides who may read).
"""

from __future__ import annotations

import json
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from roost_operator.records.bundle import MANIFEST, PART, Bundle
from roost_operator.records.planning import safe_path

SUMMARY_KEYS = ("bundle", "state", "message", "readyAt", "mission", "vehicles", "missing")


def summaries(directory: Path) -> list[dict[str, Any]]:
    """Every bundle's manifest without its file list, newest first."""
    found = []
    if directory.is_dir():
        for entry in directory.iterdir():
            manifest = Bundle(entry).manifest() if entry.is_dir() else {}
            if manifest:
                found.append({k: manifest.get(k) for k in SUMMARY_KEYS})
    return sorted(
        found,
        key=lambda m: str((m.get("mission") or {}).get("completionTime") or ""),
        reverse=True,
    )


def resolve(directory: Path, route: str) -> Path | None:
    """The file ``/bundles/<bundle>/<path>`` names, if it is one inside a bundle."""
    parts = route.strip("/").split("/", 2)
    if len(parts) != 3 or parts[0] != "bundles":
        return None
    _, bundle, relative = parts
    if not (safe_path(bundle) and "/" not in bundle and safe_path(relative)):
        return None
    if relative.endswith((PART, ".tmp")):
        return None
    path = directory / bundle / relative
    return path if path.is_file() else None


def _handler(directory: Path) -> type[BaseHTTPRequestHandler]:
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
            route = unquote(urlsplit(self.path).path)
            if route.rstrip("/") == "/bundles":
                self._json(HTTPStatus.OK, {"bundles": summaries(directory)})
                return
            path = resolve(directory, route)
            if path is None:
                self._json(HTTPStatus.NOT_FOUND, {"error": f"no such bundle file: {route}"})
                return
            size = path.stat().st_size
            offset = _offset(self.headers.get("Range"))
            if offset is not None and offset >= size > 0:
                self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                self.send_header("Content-Range", f"bytes */{size}")
                self.end_headers()
                return
            start = offset or 0
            self.send_response(HTTPStatus.PARTIAL_CONTENT if offset else HTTPStatus.OK)
            if offset:
                self.send_header("Content-Range", f"bytes {start}-{size - 1}/{size}")
            content = "application/json" if path.suffix == ".json" else "application/octet-stream"
            self.send_header("Content-Type", content)
            self.send_header("Content-Length", str(size - start))
            self.end_headers()
            with path.open("rb") as handle:
                handle.seek(start)
                while block := handle.read(1 << 16):
                    self.wfile.write(block)

    return Handler


def _offset(header: str | None) -> int | None:
    """N of ``bytes=N-`` (None: no usable Range header, the whole file is sent)."""
    if not header or not header.startswith("bytes=") or not header.endswith("-"):
        return None
    text = header[len("bytes=") : -1]
    return int(text) if text.isdigit() else None


def serve(directory: Path, address: str, port: int) -> ThreadingHTTPServer:
    """Start serving in a daemon thread; the server (``server_address`` has the port)."""
    server = ThreadingHTTPServer((address, port), _handler(directory))
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name="records-server", daemon=True).start()
    return server


__all__ = ["MANIFEST", "serve", "summaries"]
