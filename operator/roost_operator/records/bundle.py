"""A bundle on the records volume: one directory per Mission, written by the operator.

Layout (docs/mission-records.md)::

    <records dir>/<bundle>/
        manifest.json                      what is here, with sha256; what is missing and why
        mission.json                       the Mission as it ended (spec, status, conditions)
        events.json                        the Mission's Events
        vehicles/<vehicle>/<flightId>/     one flight as the agent recorded it
            flight.json, hub.tlog, decisions.jsonl, params/..., autopilot-logs/...

Downloads go to ``<file>.part`` and are renamed once complete and verified, so a file
without ``.part`` is always whole; a cut transfer resumes from the ``.part``'s length
with ``Range: bytes=N-``. The manifest is rewritten atomically (temporary file, fsync,
rename) after every round, so a reader never sees half of one.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import urllib3

from roost_api.records import sha256_of
from roost_operator.records.planning import BundleInfo, Fetch, safe_path
from roost_operator.records.source import Endpoint, SourceError, chunks

MANIFEST = "manifest.json"
PART = ".part"


class CorruptError(Exception):
    """A downloaded file's sha256 is not the one the agent listed."""


@dataclass(frozen=True)
class Stored:
    """A file now in the bundle."""

    path: str
    bytes: int
    sha256: str


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` so a reader sees the old or the new file, whole."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    with temporary.open("wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    temporary.replace(path)


def write_json(path: Path, value: Any) -> None:
    write_atomically(
        path, json.dumps(value, indent=2, sort_keys=True, default=str).encode() + b"\n"
    )


def flight_dir(vehicle: str, flight_id: str) -> str:
    """A flight's directory inside the bundle."""
    return f"vehicles/{vehicle}/{flight_id}"


@dataclass(frozen=True)
class Bundle:
    """One Mission's bundle directory."""

    root: Path

    @property
    def name(self) -> str:
        return self.root.name

    def manifest(self) -> dict[str, Any]:
        """The manifest as last written ({} before the first round)."""
        try:
            loaded = json.loads((self.root / MANIFEST).read_text())
        except FileNotFoundError:
            return {}
        return loaded if isinstance(loaded, dict) else {}

    def download(self, endpoint: Endpoint, fetch: Fetch) -> Stored:
        """Fetch one file into the bundle, resuming a ``.part`` left by a cut transfer.

        SourceError: unreachable or cut (what came through is kept); CorruptError: the
        whole file arrived but its sha256 differs (the ``.part`` is removed, so the next
        try starts from scratch)."""
        if not (safe_path(fetch.file.path) and safe_path(fetch.flight_id)):
            raise SourceError(f"refused path {fetch.flight_id}/{fetch.file.path}")
        relative = f"{flight_dir(fetch.vehicle, fetch.flight_id)}/{fetch.file.path}"
        target = self.root / relative
        part = target.with_name(target.name + PART)
        part.parent.mkdir(parents=True, exist_ok=True)
        offset = part.stat().st_size if part.exists() else 0
        response = endpoint.get(f"records/{fetch.flight_id}/{fetch.file.path}", offset)
        try:
            self._receive(response, part, offset)
        finally:
            response.release_conn()
        digest = sha256_of(part)
        if fetch.file.sha256 and digest != fetch.file.sha256:
            part.unlink()
            raise CorruptError(
                f"{relative}: sha256 {digest[:12]}… differs from the vehicle's "
                f"{fetch.file.sha256[:12]}…"
            )
        size = part.stat().st_size
        part.replace(target)
        return Stored(relative, size, digest)

    @staticmethod
    def _receive(response: urllib3.BaseHTTPResponse, part: Path, offset: int) -> None:
        if response.status == 416 and offset > 0:
            return  # nothing beyond what the .part holds: it is whole
        if response.status not in (200, 206):
            body = b"".join(chunks(response))[:200].decode(errors="replace")
            raise SourceError(f"HTTP {response.status}: {body}")
        mode = "ab" if response.status == 206 else "wb"  # 200: the server sent it all
        received = 0
        with part.open(mode) as handle:
            try:
                for chunk in chunks(response):
                    handle.write(chunk)
                    received += len(chunk)
            except (urllib3.exceptions.HTTPError, OSError) as error:
                raise SourceError(
                    f"transfer cut after {received} bytes ({type(error).__name__}); "
                    "resumes from there"
                ) from error

    def has(self, relative: str) -> bool:
        return (self.root / relative).is_file()

    def write_flight(self, vehicle: str, flight_id: str, body: Mapping[str, Any]) -> Stored:
        """The agent's ``flight.json`` of a flight, as listed."""
        relative = f"{flight_dir(vehicle, flight_id)}/flight.json"
        return self.write_document(relative, body)

    def write_document(self, relative: str, value: Any) -> Stored:
        path = self.root / relative
        write_json(path, value)
        return Stored(relative, path.stat().st_size, sha256_of(path))

    def write_manifest(self, manifest: Mapping[str, Any]) -> None:
        write_json(self.root / MANIFEST, manifest)


def list_bundles(directory: Path) -> list[BundleInfo]:
    """Every bundle under ``directory`` with when it became final (None: gathering)."""
    found: list[BundleInfo] = []
    if not directory.is_dir():
        return found
    for entry in sorted(directory.iterdir()):
        if not entry.is_dir():
            continue
        ready = Bundle(entry).manifest().get("readyAt")
        manifest = entry / MANIFEST
        written = (
            datetime.fromtimestamp(manifest.stat().st_mtime, UTC) if manifest.exists() else None
        )
        found.append(
            BundleInfo(entry.name, datetime.fromisoformat(ready) if ready else None, written)
        )
    return found


def remove_bundle(directory: Path, name: str) -> None:
    """Remove one bundle (retention); only a direct child of ``directory``."""
    target = directory / name
    if target.parent == directory and target.is_dir():
        shutil.rmtree(target)
