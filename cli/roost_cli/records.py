"""``roost records``: list the Missions' flight records and fetch a bundle.

A bundle lives on the operator's records volume and is served read-only by the
operator (docs/mission-records.md). The CLI reaches it through the API server's pod proxy of the
operator pod, with the user's kubeconfig (``get pods/proxy`` in the operator's
namespace), or at ``--records-url`` where the operator is reachable directly (the
sandbox, a port-forward).

A download resumes: every file goes to ``<file>.part`` first, continues from its
length with ``Range: bytes=N-`` when the command is run again, and is renamed only once
its sha256 matches the manifest's. The decisions (what a Mission's status says about
its record, the rows of the list) are pure functions here; the commands in
:mod:`roost_cli.main` only print.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Protocol
from urllib.parse import quote

import urllib3

from roost_api.records import sha256_of
from roost_cli.errors import CliError

OPERATOR_LABELS = {"app.kubernetes.io/component": "operator"}
RECORDS_PORT = 9469
"""The operator's records port in the chart (``records.port``)."""
CHUNK = 1 << 16


@dataclass(frozen=True)
class RecordRow:
    """One line of ``roost records list``."""

    namespace: str
    mission: str
    phase: str
    records: str
    bundle: str
    vehicles: str
    message: str
    upload: str = ""
    """The copy in the bucket: Pending, Complete, Failed ('' when none is configured)."""


def record_rows(missions: Sequence[Mapping[str, Any]]) -> list[RecordRow]:
    """Every Mission that has a record (it flew and ended), newest first."""
    rows: list[tuple[str, RecordRow]] = []
    for body in missions:
        status = body.get("status") or {}
        records = status.get("records")
        if not records:
            continue
        per_vehicle = records.get("vehicles") or []
        done = sum(1 for v in per_vehicle if v.get("state") != "Pending")
        upload = records.get("upload") or {}
        messages = [
            records.get("message"),
            upload.get("message") and f"upload: {upload['message']}",
        ]
        rows.append(
            (
                str(status.get("completionTime") or ""),
                RecordRow(
                    namespace=body["metadata"].get("namespace", ""),
                    mission=body["metadata"]["name"],
                    phase=str(status.get("phase") or ""),
                    records=str(records.get("state") or ""),
                    bundle=str(records.get("bundle") or ""),
                    vehicles=f"{done}/{len(per_vehicle)}",
                    message="; ".join(str(m) for m in messages if m),
                    upload=str(upload.get("state") or ""),
                ),
            )
        )
    rows.sort(key=lambda pair: (pair[0], pair[1].mission), reverse=True)
    return [row for _, row in rows]


def bundle_of(body: Mapping[str, Any]) -> str:
    """The bundle a Mission's record is in, or a CliError saying why there is none."""
    name = f"{body['metadata'].get('namespace')}/{body['metadata']['name']}"
    status = body.get("status") or {}
    phase = status.get("phase") or "Pending"
    records = status.get("records")
    if not records:
        if phase in ("Succeeded", "Failed", "Aborted"):
            if not status.get("startTime"):
                raise CliError(
                    f"mission {name} never flew (it ended {phase} before starting): "
                    "there is no flight record"
                )
            raise CliError(
                f"mission {name} ended {phase} but has no record: the operator gathers "
                "records only with a records volume (chart value records.enabled)"
            )
        raise CliError(f"mission {name} is {phase}: its record is gathered once it ends")
    state = records.get("state")
    if state == "Failed":
        raise CliError(f"mission {name}: the record could not be written: {records.get('message')}")
    if state == "Gathering":
        raise CliError(
            f"mission {name}: the record is still being gathered ({records.get('message')}); "
            "run this again once `roost records list` shows it Complete or Partial"
        )
    return str(records["bundle"])


class Server(Protocol):
    """The operator's records server."""

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse: ...


@dataclass
class DirectServer:
    base: str
    pool: urllib3.PoolManager = field(default_factory=urllib3.PoolManager)

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse:
        try:
            return self.pool.request(
                "GET",
                self.base.rstrip("/") + "/" + quote(path),
                headers={"Range": f"bytes={offset}-"} if offset else {},
                preload_content=False,
                retries=False,
                timeout=urllib3.Timeout(connect=5.0, read=60.0),
            )
        except urllib3.exceptions.HTTPError as error:
            raise CliError(f"the records server at {self.base} did not answer: {error}") from None


@dataclass
class ProxyServer:
    """Through the API server's pod proxy of the operator pod."""

    kube: Any
    namespace: str
    pod: str
    port: int = RECORDS_PORT

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse:
        route = f"/api/v1/namespaces/{self.namespace}/pods/{self.pod}:{self.port}/proxy/"
        headers = {"Range": f"bytes={offset}-"} if offset else {}
        try:
            return self.kube.get_bytes(route + quote(path), headers=headers).raw  # type: ignore[no-any-return]
        except Exception as error:
            raise CliError(f"the operator's records server did not answer: {error}") from None


def _chunks(response: urllib3.BaseHTTPResponse) -> Iterator[bytes]:
    body = getattr(response, "_body", None)
    if body:
        yield bytes(body)
        return
    yield from response.stream(CHUNK)


def read_json(server: Server, path: str) -> Any:
    response = server.get(path)
    try:
        body = b"".join(_chunks(response))
    finally:
        response.release_conn()
    if response.status == 404:
        raise CliError(f"{path}: not on the operator's records volume (removed by retention?)")
    if response.status != 200:
        raise CliError(f"{path}: HTTP {response.status}: {body[:200].decode(errors='replace')}")
    return json.loads(body)


@dataclass
class Fetched:
    """What ``roost records get`` wrote."""

    directory: Path
    files: int = 0
    bytes: int = 0
    missing: list[str] = field(default_factory=list)


def _safe(path: str) -> bool:
    pure = PurePosixPath(path)
    return bool(path) and not pure.is_absolute() and ".." not in pure.parts


def fetch_file(server: Server, bundle: str, entry: Mapping[str, Any], out: Path) -> Path:
    """One file of the bundle's manifest into ``out`` (kept when already whole; resumed
    from a ``.part``); CliError when cut or when its sha256 differs."""
    path = str(entry["path"])
    if not _safe(path):
        raise CliError(f"bundle {bundle}: refused path {path!r} in its manifest")
    target = out / path
    if target.is_file() and sha256_of(target) == entry.get("sha256"):
        return target
    part = target.with_name(target.name + ".part")
    part.parent.mkdir(parents=True, exist_ok=True)
    offset = part.stat().st_size if part.exists() else 0
    response = server.get(f"bundles/{bundle}/{path}", offset)
    try:
        if response.status not in (200, 206, 416):
            raise CliError(f"bundle {bundle}: {path}: HTTP {response.status}")
        if response.status != 416:
            with part.open("ab" if response.status == 206 else "wb") as handle:
                try:
                    for chunk in _chunks(response):
                        handle.write(chunk)
                except urllib3.exceptions.HTTPError as error:
                    raise CliError(
                        f"bundle {bundle}: {path}: transfer cut ({error}); run the "
                        "command again to resume"
                    ) from None
    finally:
        response.release_conn()
    if sha256_of(part) != entry.get("sha256"):
        part.unlink()
        raise CliError(f"bundle {bundle}: {path}: sha256 differs from the manifest's")
    part.replace(target)
    return target


def download(server: Server, bundle: str, out: Path) -> Fetched:
    """Every file of the bundle into ``out`` (resuming, sha256-checked), then its manifest."""
    manifest = read_json(server, f"bundles/{bundle}/manifest.json")
    result = Fetched(out)
    for entry in manifest.get("files") or []:
        target = fetch_file(server, bundle, entry, out)
        result.files += 1
        result.bytes += target.stat().st_size
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    for item in manifest.get("missing") or []:
        where = "/".join(str(item[k]) for k in ("vehicle", "flightId", "path") if item.get(k))
        result.missing.append(f"{where}: {item.get('reason')}")
    return result
