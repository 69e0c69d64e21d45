"""The agent's MAVLink signing: which key, which policy, and a timestamp that survives restarts.

Why a key file and not the RedundantAutopilot: the spec, status and Events are readable by
anyone who can read the object; a signing key must not be. By default the chart mounts
a host directory where the Vehicle's key pod (:mod:`roost_agent.keysync`) leaves
``DIR/<vehicle>/key`` and ``previous`` from its Secret (``roost keys create``) on that
vehicle's node only; older layouts mount each listed Vehicle's Secret at
``DIR/<vehicle>/``, or one fleet Secret with one entry per Vehicle at ``DIR/<vehicle>``.
The agent reads only its own vehicle's, and follows it (:class:`KeyWatcher`): a rotated
key is taken without a restart, the previous key still accepted. The key is never logged, never
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

import logging
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
KEY_ENTRY = "key"  # in a per-Vehicle key directory (a Secret's entries)
PREVIOUS_ENTRY = "previous"
KEY_POLL_S = 5.0

log = logging.getLogger(__name__)


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
    previous: bytes | None = field(default=None, repr=False)  # before the last rotation

    def signer(self, link_id: int) -> Signer:
        """A signer for one link (MAVLink link ids are per link, timestamps per system)."""
        return Signer(self.key, link_id, self.clock)

    def verifier(self) -> Verifier:
        """A verifier with its own per-stream timestamps (one per link); it also takes
        frames signed with the previous key, until the next rotation."""
        return Verifier(self.key, self.clock, self.previous)

    def rotated(self, key: bytes, previous: bytes | None) -> LinkSigning:
        """The same policy and timestamps with another key."""
        return LinkSigning(key=key, require=self.require, clock=self.clock, previous=previous)


def key_path(key_dir: Path, vehicle: str) -> Path:
    """Where the vehicle's key is mounted: a file named after the Vehicle, or a directory
    named after it with ``key`` and, after a rotation, ``previous`` (a per-Vehicle
    Secret's entries, see ``roost keys``)."""
    return key_dir / vehicle


def read_keys(key_dir: Path, vehicle: str) -> tuple[bytes, bytes | None] | None:
    """The vehicle's (key, previous key or None); None when it has no key.

    Raises :class:`SigningError` (one line, no key material) for a malformed key.
    """
    path = key_path(key_dir, vehicle)
    previous: bytes | None = None
    if path.is_dir():
        older = path / PREVIOUS_ENTRY
        path = path / KEY_ENTRY
        if older.is_file() and older.read_bytes().strip():
            previous = _parse(older)
    if not path.is_file():
        return None
    return _parse(path), previous


def _parse(path: Path) -> bytes:
    try:
        return parse_key(path.read_bytes())
    except ValueError as exc:
        raise SigningError(f"signing key {path}: {exc}") from None
    except OSError as exc:
        raise SigningError(f"signing key {path}: {exc.strerror}") from None


def load_signing(
    mode: SigningMode, key_dir: Path, vehicle: str, state_dir: Path
) -> LinkSigning | None:
    """The signing setup for ``vehicle`` under ``mode``; None when the agent does not sign.

    Raises :class:`SigningError` (a one-line message, no key material) when ``sign`` or
    ``require`` is asked for and the key is missing or malformed.
    """
    if mode is SigningMode.OFF:
        return None
    keys = read_keys(key_dir, vehicle)
    if keys is None:
        if mode is SigningMode.AUTO:
            return None
        path = key_path(key_dir, vehicle)
        raise SigningError(f"--signing {mode.value}: no key for vehicle {vehicle!r} at {path}")
    clock = PersistentTimestamps(state_dir / SIGNING_TIMESTAMP_FILE)
    key, previous = keys
    return LinkSigning(
        key=key, require=mode is not SigningMode.SIGN, clock=clock, previous=previous
    )


class KeyWatcher:
    """Follows the vehicle's key files and hands a rotated key to ``on_rotate``.

    Why polling: a Secret volume is updated by the kubelet (an atomic swap of the
    directory's contents) within about a minute of a change, with no notification the
    container can wait on; reading two 64-byte files every few seconds costs nothing. A
    key that cannot be read or parsed is reported once and the current key kept: a
    half-written file must never take signing away from a flying vehicle.
    """

    def __init__(
        self,
        key_dir: Path,
        vehicle: str,
        current: LinkSigning,
        on_rotate: Callable[[LinkSigning], None],
    ) -> None:
        self.key_dir = key_dir
        self.vehicle = vehicle
        self.current = current
        self._on_rotate = on_rotate
        self._problem: str | None = None

    def check(self) -> bool:
        """Read the files once; True when the key changed (and ``on_rotate`` was called)."""
        try:
            keys = read_keys(self.key_dir, self.vehicle)
        except SigningError as exc:
            if str(exc) != self._problem:
                self._problem = str(exc)
                log.warning("keeping the current signing key: %s", exc)
            return False
        self._problem = None
        if keys is None or keys == (self.current.key, self.current.previous):
            return False
        self.current = self.current.rotated(*keys)
        log.info("signing key of vehicle %s rotated: signing with the new key", self.vehicle)
        self._on_rotate(self.current)
        return True

    def run(self, stop: threading.Event, every_s: float = KEY_POLL_S) -> None:
        """Check every ``every_s`` until ``stop`` is set (a thread's target)."""
        while not stop.wait(every_s):
            self.check()
