"""The agent's MAVLink signing: which key, which policy, and a timestamp that survives restarts.

Why a key file and not the RedundantAutopilot: the spec, status and Events are readable by
anyone who can read the object; a signing key must not be. The chart mounts a Secret (one
entry per vehicle, named after the Vehicle, 64 hex digits) into the agent pod as a
directory; the agent reads only its own vehicle's entry. The key is never logged, never
part of an error message and never written anywhere by the agent.

Why the timestamp is persisted: the MAVLink signing specification requires that a sender's
timestamps never go backwards, or a receiver rejects its frames as replays (and an
attacker who recorded old frames could replay them after a clock reset). A companion
computer may boot without a real-time clock, so the wall clock alone cannot promise that.
The agent keeps a *reservation* in its state directory: before it issues a timestamp
beyond the reserved value it writes (atomically, fsync'd) a new reservation
:data:`RESERVE_TICKS` ahead. A restarted agent starts above the reservation, so even after
a crash every new timestamp is greater than every old one. That costs one small write per
:data:`RESERVE_TICKS` of issued time (a minute of wall clock), never one per frame.

Policies (``--signing``): ``off``; ``sign`` (sign what the agent sends, accept unsigned
frames: the step while autopilots are being provisioned); ``require`` (sign, and drop and
count every frame that is unsigned, badly signed or replayed); ``auto`` (``require`` when
the vehicle has a key, else ``off``).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from roost_mavlink.signing import TICKS_PER_S, Signer, Timestamps, Verifier, parse_key

SIGNING_TIMESTAMP_FILE = "signing-timestamp"
RESERVE_TICKS = 60 * TICKS_PER_S
DEFAULT_KEY_DIR = "/etc/roost/signing"


class SigningMode(StrEnum):
    """How the agent signs (``--signing``)."""

    AUTO = "auto"
    OFF = "off"
    SIGN = "sign"
    REQUIRE = "require"


class SigningError(ValueError):
    """The signing configuration cannot work; the message never contains key material."""


class PersistentTimestamps(Timestamps):
    """Signing timestamps that stay increasing across restarts (see the module docstring)."""

    def __init__(self, path: Path, wall: Callable[[], float] | None = None) -> None:
        self.path = path
        self._write_lock = threading.Lock()
        reserved = self._read()
        self._reserved = reserved
        if wall is None:
            super().__init__(start=reserved)
        else:
            super().__init__(start=reserved, wall=wall)

    def _read(self) -> int:
        try:
            return int(self.path.read_text().strip() or 0)
        except FileNotFoundError:
            return 0
        except ValueError as exc:
            raise SigningError(f"{self.path}: not a signing timestamp") from exc

    def _reserve(self, value: int) -> None:
        with self._write_lock:
            if value <= self._reserved:
                return
            reserved = value + RESERVE_TICKS
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            with tmp.open("w") as out:
                out.write(f"{reserved}\n")
                out.flush()
                os.fsync(out.fileno())
            tmp.replace(self.path)
            self._reserved = reserved

    def next(self) -> int:
        value = super().next()
        if value > self._reserved:
            self._reserve(value)
        return value

    def observe(self, timestamp: int) -> None:
        super().observe(timestamp)
        if timestamp > self._reserved:
            self._reserve(timestamp)

    @property
    def reserved(self) -> int:
        """The persisted bound every issued timestamp stays below."""
        return self._reserved


@dataclass(frozen=True)
class LinkSigning:
    """The key and policy every link of this agent uses (the key stays out of repr)."""

    key: bytes = field(repr=False)
    require: bool
    clock: Timestamps = field(repr=False)

    def signer(self, link_id: int) -> Signer:
        """A signer for one link (MAVLink link ids are per link, timestamps per system)."""
        return Signer(self.key, link_id, self.clock)

    def verifier(self) -> Verifier:
        """A verifier with its own per-stream timestamps (one per link)."""
        return Verifier(self.key, self.clock)


def key_path(key_dir: Path, vehicle: str) -> Path:
    """Where the vehicle's key is mounted: one file per Vehicle, named after it."""
    return key_dir / vehicle


def load_signing(
    mode: SigningMode, key_dir: Path, vehicle: str, state_dir: Path
) -> LinkSigning | None:
    """The signing setup for ``vehicle`` under ``mode``; None when the agent does not sign.

    Raises :class:`SigningError` (a one-line message, no key material) when ``sign`` or
    ``require`` is asked for and the key is missing or malformed.
    """
    if mode is SigningMode.OFF:
        return None
    path = key_path(key_dir, vehicle)
    if not path.is_file():
        if mode is SigningMode.AUTO:
            return None
        raise SigningError(f"--signing {mode.value}: no key for vehicle {vehicle!r} at {path}")
    try:
        key = parse_key(path.read_bytes())
    except ValueError as exc:
        raise SigningError(f"signing key {path}: {exc}") from None
    except OSError as exc:
        raise SigningError(f"signing key {path}: {exc.strerror}") from None
    clock = PersistentTimestamps(state_dir / SIGNING_TIMESTAMP_FILE)
    return LinkSigning(key=key, require=mode is not SigningMode.SIGN, clock=clock)
