"""``roost dashboard``: the ASGI app (starlette, served by uvicorn) and how it is run.

Routes:

* ``GET /`` — the single page (``static/index.html``; everything it loads ships in this
  package, nothing is fetched from the internet);
* ``WS /ws`` — the fleet document (:meth:`~.model.FleetModel.snapshot`), pushed when
  something changed, at most :data:`PUSH_HZ` times a second: at once when the last push
  is older than a period, else at the end of it;
* ``POST /api/abort`` and ``POST /api/estop`` — the guarded actions
  (:mod:`.actions_api`), refused with ``--read-only``;
* ``GET /records`` — the Missions' flight records and a flight's plot
  (``static/records.html``), over ``GET /api/records…`` (:mod:`.records_api`).

Who acts: the dashboard has no identity of its own. It reads and writes with the
kubeconfig of the user who runs it (the same resolution as every ``roost`` command), so
RBAC decides what a dashboard user may do exactly as it does for ``roost abort`` and
``roost estop``; ``--read-only`` removes the actions (the chart's Deployment always runs
read-only). Requests that change something must carry the page's per-run token in a
header (a page from another origin can neither read it nor send the header without a
CORS preflight, which this server never grants), and the WebSocket refuses other origins.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
import socket
import sys
import tempfile
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from roost_api.telemetry import Origin
from roost_cli import records
from roost_cli.cluster import Fleet
from roost_cli.dashboard import actions_api, records_api
from roost_cli.dashboard.model import FleetModel
from roost_cli.dashboard.sources import Endpoints, TelemetryClients, start_watchers
from roost_cli.errors import CliError

log = logging.getLogger(__name__)

PUSH_HZ = 10.0
SEND_TIMEOUT_S = 2.0
TOKEN_HEADER = "x-roost-token"
DEFAULT_PORT = 8765


@dataclass
class Settings:
    """What ``roost dashboard`` was asked for."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    read_only: bool = False
    origin: Origin | None = None
    tiles: str | None = None
    """An XYZ tile URL template for an outdoor field (``{z}/{x}/{y}``); none by default."""
    records_url: str | None = None
    """The operator's records server when reachable directly (else the pod proxy)."""
    operator_namespace: str = "roost-system"
    """Where the operator runs (its pod serves the records)."""


class Pusher:
    """Sends the model to every browser, only when it changed, at most PUSH_HZ a second."""

    def __init__(self, model: FleetModel, render: Callable[[], str]) -> None:
        self.model = model
        self._render = render
        self._clients: set[WebSocket] = set()
        self._changed = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    def changed(self) -> None:
        """Called from any thread when the model changed."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._changed.set)

    async def run(self) -> None:
        self._loop = asyncio.get_running_loop()
        period = 1.0 / PUSH_HZ
        sent_version = -1
        last = 0.0
        while True:
            await self._changed.wait()
            wait = last + period - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            self._changed.clear()
            if self.model.version == sent_version or not self._clients:
                continue
            sent_version = self.model.version
            last = time.monotonic()
            text = self._render()
            for ws in list(self._clients):
                try:  # a browser that stopped reading is dropped, not waited for
                    await asyncio.wait_for(ws.send_text(text), SEND_TIMEOUT_S)
                except (RuntimeError, WebSocketDisconnect, OSError, TimeoutError):
                    self._clients.discard(ws)
                    with contextlib.suppress(RuntimeError, OSError, TimeoutError):
                        await asyncio.wait_for(ws.close(code=1011), 1.0)  # it reconnects

    async def serve(self, ws: WebSocket, first: str) -> None:
        await ws.accept()
        await ws.send_text(first)
        self._clients.add(ws)
        try:
            while True:  # the browser sends nothing; this notices it leaving
                await ws.receive_text()
        except WebSocketDisconnect:
            pass
        finally:
            self._clients.discard(ws)


def static_text(name: str) -> str:
    return resources.files("roost_cli.dashboard").joinpath("static", name).read_text()


NO_CLUSTER = "no cluster: the agents' streams only"


def build_app(
    fleet: Fleet | None,
    settings: Settings,
    endpoints: Endpoints,
) -> Starlette:
    """The dashboard app; its lifespan starts the watches, telemetry clients and pusher.

    Without a ``fleet`` (``--no-cluster``) it shows only what the agents stream, read-only.
    """
    read_only = settings.read_only or fleet is None
    server = fleet.server if fleet is not None else NO_CLUSTER
    token = secrets.token_urlsafe(24)
    pusher_box: list[Pusher] = []

    def on_change() -> None:
        if pusher_box:
            pusher_box[0].changed()

    fleet_model = FleetModel(settings.origin, on_change=on_change)

    def render() -> str:
        doc = fleet_model.snapshot(read_only=read_only, server=server)
        return json.dumps(doc, separators=(",", ":"), default=str)

    pusher = Pusher(fleet_model, render)
    pusher_box.append(pusher)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        watchers = start_watchers(fleet.kube, fleet_model) if fleet else []
        tasks = [
            asyncio.create_task(pusher.run()),
            asyncio.create_task(TelemetryClients(fleet_model, endpoints).run()),
        ]
        try:
            yield
        finally:
            for watcher in watchers:
                watcher.stop()
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    page = (
        static_text("index.html")
        .replace("__TOKEN__", token if not read_only else "")
        .replace("__TILES__", json.dumps(settings.tiles or ""))
    )

    async def index(request: Request) -> Response:
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

    async def stream(ws: WebSocket) -> None:
        origin = ws.headers.get("origin")
        host = ws.headers.get("host", "")
        if origin is not None and origin.split("://", 1)[-1] != host:
            await ws.close(code=1008)
            return
        await pusher.serve(ws, render())

    def guarded(
        handler: Callable[[Fleet, FleetModel, dict[str, Any]], dict[str, Any]],
    ) -> Callable[[Request], Any]:
        async def endpoint(request: Request) -> Response:
            if read_only or fleet is None:
                return JSONResponse({"error": "this dashboard is read-only"}, status_code=403)
            if not secrets.compare_digest(request.headers.get(TOKEN_HEADER, ""), token):
                return JSONResponse({"error": "missing or wrong token"}, status_code=403)
            try:
                body = await request.json()
            except ValueError:
                return JSONResponse({"error": "expected a JSON body"}, status_code=400)
            if not isinstance(body, dict):
                return JSONResponse({"error": "expected a JSON object"}, status_code=400)
            try:
                result = await asyncio.to_thread(handler, fleet, fleet_model, body)
            except actions_api.RefusedError as error:
                return JSONResponse({"error": str(error)}, status_code=error.status)
            return JSONResponse(result)

        return endpoint

    access = records_access(fleet, settings)

    async def records_page(request: Request) -> Response:
        return HTMLResponse(static_text("records.html"), headers={"Cache-Control": "no-store"})

    async def records_json(request: Request) -> Response:
        bundle = request.path_params.get("bundle")
        flight = request.query_params.get("flight")
        try:
            if bundle is None:
                result = await asyncio.to_thread(access.bundles)
            elif flight is None:
                result = await asyncio.to_thread(access.manifest, bundle)
            else:
                result = await asyncio.to_thread(access.plot, bundle, flight)
        except records_api.NotFoundError as error:
            return JSONResponse({"error": str(error)}, status_code=404)
        except CliError as error:
            return JSONResponse({"error": str(error)}, status_code=502)
        return JSONResponse(result, headers={"Cache-Control": "no-store"})

    routes = [
        Route("/", index),
        Route("/records", records_page),
        Route("/api/records", records_json),
        Route("/api/records/{bundle}", records_json),
        Route("/api/records/{bundle}/plot", records_json),
        Route("/api/abort", guarded(actions_api.abort), methods=["POST"]),
        Route("/api/estop", guarded(actions_api.estop), methods=["POST"]),
        WebSocketRoute("/ws", stream),
        Mount(
            "/static",
            app=StaticFiles(packages=[("roost_cli.dashboard", "static")]),
            name="static",
        ),
    ]
    app = Starlette(routes=routes, lifespan=lifespan)
    app.state.model = fleet_model
    app.state.pusher = pusher
    return app


def records_access(fleet: Fleet | None, settings: Settings) -> records_api.RecordsAccess:
    """Where the records pages read bundles from (the server is found per request, so a
    restarted operator pod is found again)."""

    def server() -> records.Server | None:
        if settings.records_url:
            return records.DirectServer(settings.records_url)
        if fleet is None:
            return None
        pod = fleet.operator_pod(settings.operator_namespace)
        return records.ProxyServer(fleet.kube, settings.operator_namespace, pod)

    made: list[Path] = []

    def cache() -> Path:
        if not made:
            made.append(Path(tempfile.mkdtemp(prefix="roost-dashboard-records-")))
        return made[0]

    return records_api.RecordsAccess(server, cache, settings.origin)


def bind(host: str, port: int) -> socket.socket:
    """The listening socket (port 0: a free one), bound before uvicorn starts."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(64)
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


def serve(
    fleet: Fleet | None,
    settings: Settings,
    endpoints: Endpoints,
    *,
    announce: Callable[[str], None] = lambda url: None,
    stop: threading.Event | None = None,
) -> None:
    """Run the dashboard until Ctrl-C/SIGTERM (or ``stop``)."""
    try:
        sock = bind(settings.host, settings.port)
    except OSError as error:
        raise CliError(
            f"cannot serve on {settings.host}:{settings.port}: {error.strerror or error} "
            "(--port 0 picks a free port)"
        ) from None
    app = build_app(fleet, settings, endpoints)
    config = uvicorn.Config(app, log_level="warning", lifespan="on", ws="websockets-sansio")
    server = uvicorn.Server(config)
    announce(url_of(sock))
    sys.stdout.flush()
    if stop is not None:

        def watch_stop() -> None:
            stop.wait()
            server.should_exit = True

        threading.Thread(target=watch_stop, daemon=True).start()
    server.run(sockets=[sock])
