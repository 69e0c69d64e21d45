"""Control socket: how ``roost-sim fault`` reaches an autopilot in a running ``roost-sim run``.

One unix stream socket per simulated autopilot, ``<state dir>/<name>.sock``. A unix
socket (not a TCP port) because it needs no free port, is private to the user (the
directory is 0700) and its path names the target. The state directory is
``$ROOST_SIM_STATE_DIR`` or ``/tmp/roost-sim-<uid>``.

Protocol: the client sends one JSON object on one line and reads one line back.

- ``{"op": "fault", "kind": "sensor", "value": "gyro"}``
- ``{"op": "clear", "kind": null}`` (null = every fault)
- ``{"op": "status"}``
- ``{"op": "fly", "value": 10, "timeout": 5}`` (arm and take off to ``value`` metres,
  default the configured takeoff altitude, once the autopilot has finished starting up --
  waiting at most ``timeout`` seconds, default 5: what a mission's controller would do;
  the sandbox uses it)
- ``{"op": "throttle", "value": 0.5}`` (the pilot's throttle stick 0..1; null: no RC)

Every answer is ``{"ok": true, "state": <SimSnapshot>}`` or ``{"ok": false, "error": ...}``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import socket
import threading
from pathlib import Path
from typing import Any

from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.faults import FaultKind

_log = logging.getLogger(__name__)

_MAX_REQUEST_BYTES = 4096
DEFAULT_FLY_WAIT_S = 5.0


def state_dir() -> Path:
    """Where control sockets live (created 0700 on first use)."""
    path = Path(os.environ.get("ROOST_SIM_STATE_DIR") or f"/tmp/roost-sim-{os.getuid()}")
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    return path


def socket_path(name: str, directory: Path | None = None) -> Path:
    """Control socket of the autopilot called ``name``."""
    return (directory or state_dir()) / f"{name}.sock"


def handle_request(sim: SimulatedAutopilot, request: dict[str, Any]) -> dict[str, Any]:
    """Apply one control request to ``sim``; the answer to send back.

    A refused or invalid request is answered ``{"ok": false, "error": ...}``; it never
    raises, so one bad request cannot take the control socket down.
    """
    try:
        op = request.get("op")
        if op == "fault":
            sim.inject(FaultKind(request["kind"]), request.get("value"))
        elif op == "clear":
            kind = request.get("kind")
            sim.clear(FaultKind(kind) if kind else None)
        elif op == "fly":
            _fly(sim, request)
        elif op == "throttle":
            value = request.get("value")
            sim.set_throttle(None if value is None else _number(value, "throttle"))
        elif op != "status":
            raise ValueError(f"unknown op {op!r}")
    except KeyError as exc:
        return {"ok": False, "error": f"missing field {exc}"}
    except (ValueError, TypeError, RuntimeError) as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "state": sim.snapshot().to_json()}


def _number(value: Any, what: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, not {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{what} must be finite, not {value!r}")
    return number


def _fly(sim: SimulatedAutopilot, request: dict[str, Any]) -> None:
    """Like a mission controller: wait for start-up to finish, then arm and take off."""
    value = request.get("value")
    altitude = None if value is None else _number(value, "altitude")
    timeout = _number(request.get("timeout", DEFAULT_FLY_WAIT_S), "timeout")
    try:
        sim.wait_ready(timeout=timeout)
    except TimeoutError:
        snap = sim.snapshot()
        raise RuntimeError(
            f"{sim.name} is still starting up ({snap.system_status}, "
            f"{snap.time_boot_ms / 1000:.1f} s after boot) and refuses to arm; "
            f"try again later or start it with --fast-boot"
        ) from None
    sim.fly(altitude)


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
        sock.listen(4)  # blocking accept: stop() wakes it by shutting the socket down
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="sim-control", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and remove the socket file."""
        self._stop.set()
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept
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
                except Exception as exc:  # the socket must outlive any one request
                    _log.exception("control request failed")
                    answer = {"ok": False, "error": f"internal error: {exc}"}
                with contextlib.suppress(OSError):
                    conn.sendall(json.dumps(answer).encode() + b"\n")


def _alive(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(str(path))
        except OSError:
            return False
        return True


def request(path: Path, message: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
    """Send one request to a control socket and return the decoded answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(str(path))
        sock.sendall(json.dumps(message).encode() + b"\n")
        answer = json.loads(sock.makefile("rb").readline())
    if not isinstance(answer, dict):
        raise ValueError(f"unexpected answer from {path}: {answer!r}")
    return answer
