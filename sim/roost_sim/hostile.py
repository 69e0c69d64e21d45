"""A hostile MAVLink sender on the loopback interface, for tests and benchmarks.

Why it exists: the agent must trust only its autopilots, and that is only shown by
putting someone it must not trust beside them. This sender shares the host with the
simulated autopilots and sends, to the agent's own ports, what an attacker or a broken
second sender would: random bytes, truncated frames, frames with a bad CRC, and valid
frames that claim the autopilot's system and component id (a low ``time_boot_ms``
ATTITUDE that looks like a reboot, EMERGENCY heartbeats), mixed into single datagrams
and sent as datagrams of their own. It also listens: every datagram the agent sends to
it is counted, and there must be none.

It sends only to 127.0.0.1 and stops after ``duration_s`` at the latest, so a flood can
never outlive the test or benchmark that started it.
"""

from __future__ import annotations

import os
import random
import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from roost_mavlink.status import MavState

LOOPBACK = "127.0.0.1"
MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12


@dataclass(frozen=True)
class Target:
    """An agent port and the identity of the autopilot the agent expects there."""

    port: int
    sysid: int
    component_id: int = 1


def hostile_datagrams(target: Target, rng: random.Random) -> list[bytes]:
    """One round of hostile traffic against one target (seven datagrams)."""
    spoof = mavlink.MAVLink(None, srcSystem=target.sysid, srcComponent=target.component_id)
    spoof.seq = rng.randrange(256)
    emergency = spoof.heartbeat_encode(
        MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, 129, 0, int(MavState.EMERGENCY)
    ).pack(spoof)
    rebooted = spoof.attitude_encode(5, 0.1, 0.1, 0, 0, 0, 0).pack(spoof)
    bad_crc = bytearray(rebooted)
    bad_crc[-1] ^= 0xFF
    garbage = os.urandom(rng.randrange(8, 200))
    truncated = emergency[: len(emergency) // 2]
    return [
        garbage,
        truncated,
        bytes(bad_crc),
        emergency,
        rebooted,
        garbage[:16] + rebooted + truncated,  # garbage and a truncated tail around a frame
        truncated + emergency + bytes(bad_crc),
    ]


class HostileSender:
    """Sends hostile datagrams to ``targets`` at ``rounds_per_s`` (each round: seven per
    target) until stopped or ``duration_s`` passed; counts what comes back."""

    def __init__(
        self,
        targets: list[Target],
        *,
        rounds_per_s: float = 10.0,
        duration_s: float = 120.0,
        seed: int = 1,
    ) -> None:
        self.targets = targets
        self.rounds_per_s = rounds_per_s
        self.duration_s = duration_s
        self.sent = 0
        self.received: list[tuple[bytes, Any]] = []
        self._rng = random.Random(seed)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((LOOPBACK, 0))
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._send_forever, name="hostile-send", daemon=True),
            threading.Thread(target=self._listen_forever, name="hostile-listen", daemon=True),
        ]

    @property
    def address(self) -> tuple[str, int]:
        """Where the hostile sender sends from (and listens)."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def start(self) -> HostileSender:
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        self._sock.close()

    def __enter__(self) -> HostileSender:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _send_forever(self) -> None:
        start = time.monotonic()
        period = 1.0 / self.rounds_per_s
        rounds = 0
        # Prepared once: a flood measures the receiver, not this sender's encoding.
        prepared = {t: hostile_datagrams(t, self._rng) for t in self.targets}
        while not self._stop.is_set():
            now = time.monotonic()
            if now - start >= self.duration_s:
                return
            due = start + rounds * period
            if due > now:
                self._stop.wait(min(due - now, 0.05))
                continue
            for target in self.targets:
                batch = prepared[target] if rounds % 16 else hostile_datagrams(target, self._rng)
                for datagram in batch:
                    try:
                        self._sock.sendto(datagram, (LOOPBACK, target.port))
                        self.sent += 1
                    except OSError:  # the receiver's buffer is full: a flood does that
                        pass
            rounds += 1

    def _listen_forever(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._sock], [], [], 0.1)
                if ready:
                    self.received.append(self._sock.recvfrom(65535))
            except (OSError, ValueError):
                return
