"""The records HTTP server on a real socket: listing, files, ranges, 404s, traversal."""

from __future__ import annotations

import http.client
import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from roost_agent.records import FileEntry, Manifest, write_manifest
from roost_agent.records_server import RecordsServer
from roost_api.records import FileKind
from tests.unit.test_agent_records import T0


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[RecordsServer, Path]]:
    root = tmp_path / "records"
    for n, second in enumerate((0, 30)):
        manifest = Manifest(f"v-2026112720000{n}Z", "v", T0.replace(second=second))
        (root / manifest.flight_id).mkdir(parents=True)
        (root / manifest.flight_id / "hub.tlog").write_bytes(bytes(range(256)) * 4)
        write_manifest(root, manifest.with_file(FileEntry("hub.tlog", FileKind.TLOG)))
    (tmp_path / "secret").write_text("no")
    server = RecordsServer(root, "v")
    try:
        yield server, root
    finally:
        server.close()


def _get(server: RecordsServer, path: str, **headers: str) -> tuple[int, dict[str, str], bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        conn.request("GET", path, headers=headers)
        response = conn.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        conn.close()


def test_listing_is_newest_first(served: tuple[RecordsServer, Path]) -> None:
    server, _ = served
    status, _, body = _get(server, "/records")
    doc = json.loads(body)
    assert status == 200
    assert doc["vehicle"] == "v"
    assert [f["flightId"] for f in doc["flights"]] == ["v-20261127200001Z", "v-20261127200000Z"]


def test_files_whole_and_resumed_with_a_range(served: tuple[RecordsServer, Path]) -> None:
    server, root = served
    whole = (root / "v-20261127200000Z" / "hub.tlog").read_bytes()
    status, headers, body = _get(server, "/records/v-20261127200000Z/hub.tlog")
    assert (status, body, headers["Accept-Ranges"]) == (200, whole, "bytes")
    status, headers, body = _get(server, "/records/v-20261127200000Z/hub.tlog", Range="bytes=1000-")
    assert (status, body) == (206, whole[1000:])
    assert headers["Content-Range"] == f"bytes 1000-{len(whole) - 1}/{len(whole)}"
    status, headers, _ = _get(server, "/records/v-20261127200000Z/hub.tlog", Range="bytes=5000-")
    assert (status, headers["Content-Range"]) == (416, f"bytes */{len(whole)}")
    status, _, body = _get(server, "/records/v-20261127200000Z/flight.json")
    assert status == 200
    assert json.loads(body)["flightId"] == "v-20261127200000Z"


@pytest.mark.parametrize(
    "path",
    [
        "/records/v-20261127200000Z/missing",
        "/records/nope/flight.json",
        "/records/v-20261127200000Z/../../secret",
        "/records/v-20261127200000Z/%2e%2e/%2e%2e/secret",
        "/records/..%2fsecret/x",
        "/elsewhere",
    ],
)
def test_unknown_and_outside_paths_are_404_json(
    served: tuple[RecordsServer, Path], path: str
) -> None:
    server, _ = served
    status, headers, body = _get(server, path)
    assert status == 404
    assert headers["Content-Type"] == "application/json"
    assert "error" in json.loads(body)
