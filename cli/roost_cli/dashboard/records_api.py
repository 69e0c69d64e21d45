"""The dashboard's records routes: the Missions' bundles and one flight's plot.

The bundles come from the operator's records server (``--records-url``, or the API
server's pod proxy of the operator pod with the dashboard's kubeconfig), file by file
into a cache directory, sha256-checked like ``roost records get``; a flight is parsed
once per request (:mod:`.flightplot`) — a flight's tlog is read in about a second.

``GET /api/records`` → ``{"bundles": [...]}``; ``GET /api/records/<bundle>`` → its
manifest; ``GET /api/records/<bundle>/plot?flight=<flightId>`` → the plot document.
Errors are JSON ``{"error": ...}``: 404 when there is no such bundle or flight, 502 when
the records server cannot be reached.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roost_api.telemetry import Origin
from roost_cli import records
from roost_cli.dashboard.flightplot import plot_document
from roost_cli.errors import CliError


class NotFoundError(Exception):
    """No such bundle or flight."""


@dataclass
class RecordsAccess:
    """Reads bundles from ``server()`` (None: no records server known) into a cache
    directory made on first use (``cache()``), so a dashboard on a read-only root
    filesystem without a scratch volume still serves everything but the plots."""

    server: Callable[[], records.Server | None]
    cache: Callable[[], Path]
    origin: Origin | None = None

    def _server(self) -> records.Server:
        found = self.server()
        if found is None:
            raise CliError("no records server: run the dashboard with a cluster, or --records-url")
        return found

    def bundles(self) -> dict[str, Any]:
        listed: dict[str, Any] = records.read_json(self._server(), "bundles")
        return listed

    def manifest(self, bundle: str) -> dict[str, Any]:
        if "/" in bundle or bundle.startswith("."):
            raise NotFoundError(f"no bundle {bundle!r}")
        try:
            doc: dict[str, Any] = records.read_json(
                self._server(), f"bundles/{bundle}/manifest.json"
            )
        except CliError as error:
            if "not on the operator's records volume" in str(error):
                raise NotFoundError(f"no bundle {bundle!r}") from None
            raise
        return doc

    def plot(self, bundle: str, flight_id: str) -> dict[str, Any]:
        manifest = self.manifest(bundle)
        flight = next(
            (f for f in manifest.get("flights") or [] if f["flightId"] == flight_id), None
        )
        if flight is None:
            raise NotFoundError(f"bundle {bundle} has no flight {flight_id!r}")
        files = {
            f.get("name"): f for f in manifest.get("files") or [] if f.get("flightId") == flight_id
        }
        try:
            out = self.cache() / bundle
        except OSError as error:
            raise CliError(f"no scratch directory for the flight's files: {error}") from None
        server = self._server()

        def local(name: str) -> Path | None:
            entry = files.get(name)
            return records.fetch_file(server, bundle, entry, out) if entry else None

        tlog = local("hub.tlog")
        decisions_path = local("decisions.jsonl")
        params: dict[str, Mapping[str, Any]] = {}
        for name, entry in files.items():
            if name and name.startswith("params/") and entry.get("autopilot"):
                path = local(name)
                if path is not None:
                    params[str(entry["autopilot"])] = json.loads(path.read_text())
        decisions = decisions_path.read_text() if decisions_path is not None else ""
        doc = plot_document(tlog, decisions, params, self.origin)
        doc.update(
            flight=flight_id,
            vehicle=flight.get("vehicle"),
            state=flight.get("state"),
            missing=[m for m in manifest.get("missing") or [] if m.get("flightId") == flight_id],
        )
        return doc
