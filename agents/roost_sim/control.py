"""Control socket: how ``roost-sim fault`` reaches an autopilot in a running ``roost-sim run``.

One unix stream socket per simulated autopilot, ``<state dir>/<name>.sock``. A unix
socket (not a TCP port) because it needs no free port, is private to the user (the
directory is 0700) and its path names the target. The state directory is
``$ROOST_SIM_STATE_DIR`` or ``/tmp/roost-sim-<uid>``.

Protocol: the client sends one JSON object on one line and reads one line back.

- ``{"op": "fault", "kind": "sensor", "value": "gyro"}``
- ``{"op": "clear", "kind": null}`` (null = every fault)
- ``{"op": "status"}``
- ``{"op": "fly", "value": 10}`` (arm and take off to ``value`` metres, default the
  configured takeoff altitude, once the autopilot has booted: what a mission's controller
  would do; the sandbox uses it)

Every answer is ``{"ok": true, "state": <SimSnapshot>}`` or ``{"ok": false, "error": ...}``.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
from pathlib import Path
from typing import Any

from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.faults import FaultKind

_MAX_REQUEST_BYTES = 4096


def state_dir() -> Path:
    """Where control sockets live (created 0700 on first use)."""
    path = Path(os.environ.get("ROOST_SIM_STATE_DIR") or f"/tmp/roost-sim-{os.getuid()}")
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    return path


def socket_path(name: str, directory: Path | None = None) -> Path:
    """Control socket of the autopilot called ``name``."""
    return (directory or state_dir()) / f"{name}.sock"


def handle_request(sim: SimulatedAutopilot, request: dict[str, Any]) -> dict[str, Any]:
    """Apply one control request to ``sim``; the answer to send back."""
    try:
        op = request.get("op")
        if op == "fault":
            sim.inject(FaultKind(request["kind"]), request.get("value"))
        elif op == "clear":
            kind = request.get("kind")
            sim.clear(FaultKind(kind) if kind else None)
        elif op == "fly":
            value = request.get("value")
            # Like a mission controller, wait for the autopilot to finish booting: right
            # after start it refuses to arm, which made an early request fail at random.
            sim.wait_until(lambda snap: snap.system_status != "BOOT", timeout=5.0)
            sim.fly(float(value) if value is not None else None)
        elif op != "status":
            raise ValueError(f"unknown op {op!r}")
    except (KeyError, ValueError) as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "state": sim.snapshot().to_json()}


class ControlServer:
    """Serves :func:`handle_request` for one sim on a unix socket."""

    def __init__(self, sim: SimulatedAutopilot, path: Path) -> None:
        self.sim = sim
        self.path = path
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> ControlServer:
        """Bind the socket (replacing a stale one) and serve in a thread."""
        if self.path.exists():
            if _alive(self.path):
                raise RuntimeError(f"{self.path} is served by another running sim")
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(str(self.path))
        sock.listen(4)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="sim-control", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and remove the socket file."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self._sock is not None:
            self._sock.close()
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(2)
                try:
                    line = conn.makefile("rb").readline(_MAX_REQUEST_BYTES)
                    request = json.loads(line)
                    if not isinstance(request, dict):
                        raise ValueError("request must be a JSON object")
                    answer = handle_request(self.sim, request)
                except (OSError, ValueError) as exc:
                    answer = {"ok": False, "error": str(exc)}
                with contextlib.suppress(OSError):
                    conn.sendall(json.dumps(answer).encode() + b"\n")


def _alive(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(str(path))
        except OSError:
            return False
        return True


def request(path: Path, message: dict[str, Any], timeout: float = 5.0) -> dict[str, Any]:
    """Send one request to a control socket and return the decoded answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(str(path))
        sock.sendall(json.dumps(message).encode() + b"\n")
        answer = json.loads(sock.makefile("rb").readline())
    if not isinstance(answer, dict):
        raise ValueError(f"unexpected answer from {path}: {answer!r}")
    return answer
