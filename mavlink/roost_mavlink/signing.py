"""MAVLink 2 message signing on finished frames, shared by the agent and the simulator.

Why on frames and not inside pymavlink's encoder: both sides already hand finished frames
to a transport (the agent's writer, the simulator's link), so signing there covers every
frame whatever produced it; and pymavlink's own receive check records a stream's
timestamp *before* it checks the signature, so one forged frame with a far-future
timestamp would make every genuine frame of that stream look like a replay. Here a
timestamp is recorded only after its signature proved genuine.

The rules are those of the MAVLink signing specification:

- a signed frame is a MAVLink 2 frame with ``incompat_flags`` bit 0x01 set (the CRC covers
  the header, so it is recomputed) followed by a 13-byte block: link id (1 byte),
  timestamp (6 bytes, little endian, units of 10 microseconds since 2015-01-01 00:00 UTC)
  and the first 6 bytes of SHA-256(secret key + frame + link id + timestamp);
- a timestamp never repeats or goes backwards for one sender: the :class:`Timestamps`
  source is strictly increasing (the agent persists it across restarts, see
  ``roost_agent.signing``);
- a receiver keeps the last timestamp per stream (link id, system id, component id) and
  rejects a frame that does not advance it; a stream it has not seen is accepted when its
  timestamp is no more than one minute behind the receiver's own clock.

CRC_EXTRA comes from :mod:`roost_mavlink.codec` (no pymavlink). SHA-256 is ``hashlib``'s,
imported on first use: ``hashlib`` (and ``hmac``, which imports it) maps libcrypto,
megabytes of an agent's memory that an agent without signing does not need.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from enum import StrEnum

from roost_mavlink.codec import crc_extra_of, frame_crc

KEY_BYTES = 32
SIGNATURE_BLOCK = 13
V2_MARKER = 0xFD
V1_MARKER = 0xFE
V2_HEADER = 10
V1_HEADER = 6
IFLAG_SIGNED = 0x01
EPOCH_2015_UNIX_S = 1420070400
TICKS_PER_S = 100_000  # one tick = 10 microseconds
NEW_STREAM_SLACK_TICKS = 60 * TICKS_PER_S  # the specification's one minute


def unix_to_ticks(unix_s: float) -> int:
    """A Unix time in signing timestamp units (10 us since 2015-01-01 UTC)."""
    return max(0, int((unix_s - EPOCH_2015_UNIX_S) * TICKS_PER_S))


class Timestamps:
    """A strictly increasing signing timestamp that follows the wall clock where it can."""

    def __init__(self, start: int = 0, wall: Callable[[], float] = time.time) -> None:
        self._lock = threading.Lock()
        self._last = start
        self._wall = wall

    def current(self) -> int:
        """The latest timestamp issued or seen (what new streams are compared with)."""
        with self._lock:
            return max(self._last, unix_to_ticks(self._wall()))

    def next(self) -> int:
        """A timestamp greater than every one issued before."""
        with self._lock:
            self._last = max(self._last + 1, unix_to_ticks(self._wall()))
            return self._last

    def observe(self, timestamp: int) -> None:
        """A genuine timestamp from a peer: never issue one below it (the spec's rule)."""
        with self._lock:
            self._last = max(self._last, timestamp)


def parse_key(text: str | bytes) -> bytes:
    """A 32-byte secret key from its 64-hex-digit text form (whitespace ignored).

    Raises ValueError without ever quoting the text (it is a secret).
    """
    raw = text.decode("ascii", "replace") if isinstance(text, bytes) else text
    digits = "".join(raw.split())
    if len(digits) != 2 * KEY_BYTES:
        raise ValueError(f"a signing key is {2 * KEY_BYTES} hex digits, got {len(digits)}")
    try:
        return bytes.fromhex(digits)
    except ValueError:
        raise ValueError("a signing key is hex digits only") from None


def passphrase_key(passphrase: str) -> bytes:
    """The 32-byte key ground stations derive from a passphrase: SHA-256 of its ASCII
    text (MAVProxy's ``signing key PASSPHRASE``; QGroundControl's signing key field)."""
    import hashlib  # noqa: PLC0415 - only with signing on (see the module docstring)

    return hashlib.sha256(passphrase.encode("ascii")).digest()


def _crc(data: bytes, msg_id: int) -> int | None:
    crc_extra = crc_extra_of(msg_id)
    return None if crc_extra is None else frame_crc(data, crc_extra)


def frame_length(buf: bytes | bytearray, start: int = 0) -> int | None:
    """Length of the frame beginning at ``start`` (None: not a frame start or too short)."""
    if len(buf) - start < 3:
        return None
    marker = buf[start]
    if marker == V2_MARKER:
        signed = SIGNATURE_BLOCK if buf[start + 2] & IFLAG_SIGNED else 0
        return V2_HEADER + buf[start + 1] + 2 + signed
    if marker == V1_MARKER:
        return V1_HEADER + buf[start + 1] + 2
    return None


def split_frames(data: bytes) -> list[bytes]:
    """Whole frames found in ``data`` (bytes between or after them are skipped)."""
    frames: list[bytes] = []
    i = 0
    while i < len(data):
        length = frame_length(data, i)
        if length is None or i + length > len(data):
            i += 1
            continue
        frames.append(data[i : i + length])
        i += length
    return frames


def sign_frame(frame: bytes, key: bytes, link_id: int, timestamp: int) -> bytes:
    """The MAVLink 2 ``frame`` signed (an existing signature is replaced).

    A MAVLink 1 frame or an unknown message id is returned unchanged: neither can carry a
    signature a receiver could check.
    """
    if len(frame) < V2_HEADER + 2 or frame[0] != V2_MARKER:
        return frame
    length = frame[1]
    msg_id = frame[7] | frame[8] << 8 | frame[9] << 16
    body = bytearray(frame[: V2_HEADER + length])
    body[2] |= IFLAG_SIGNED
    crc = _crc(bytes(body[1:]), msg_id)
    if crc is None:
        return frame
    signed = bytes(body) + struct.pack("<H", crc) + bytes([link_id & 0xFF])
    signed += struct.pack("<Q", timestamp)[:6]
    return signed + _signature(key + signed)


def _signature(data: bytes) -> bytes:
    """The first 6 bytes of SHA-256(``data``)."""
    import hashlib  # noqa: PLC0415 - only with signing on (see the module docstring)

    return hashlib.sha256(data).digest()[:6]


class Verdict(StrEnum):
    """What :meth:`Verifier.check` found."""

    GOOD = "good"
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad-signature"
    REPLAYED = "replayed"  # a genuine signature with a timestamp that does not advance


class Verifier:
    """Checks signed frames against one key, remembering each stream's last timestamp.

    With ``previous`` (the key before a rotation) a frame signed with either verifies,
    and :attr:`used` tells which key the last genuine frame was signed with, so the
    receiver can answer each peer with the key it has (an autopilot keeps the old key
    until it is provisioned again).
    """

    def __init__(self, key: bytes, clock: Timestamps, previous: bytes | None = None) -> None:
        if len(key) != KEY_BYTES or (previous is not None and len(previous) != KEY_BYTES):
            raise ValueError(f"a signing key is {KEY_BYTES} bytes")
        self._key = key
        self._previous = previous
        self._clock = clock
        self._streams: dict[tuple[int, int, int], int] = {}
        self.used = key

    def check(self, frame: bytes | bytearray) -> Verdict:
        """Judge one whole frame (as received, signature block included)."""
        if len(frame) < V2_HEADER + 2 + SIGNATURE_BLOCK or frame[0] != V2_MARKER:
            return Verdict.UNSIGNED
        if not frame[2] & IFLAG_SIGNED:
            return Verdict.UNSIGNED
        data = bytes(frame)
        import hmac  # noqa: PLC0415 - only with signing on (see the module docstring)

        key = self._key
        if not hmac.compare_digest(_signature(key + data[:-6]), data[-6:]):
            previous = self._previous
            if previous is None or not hmac.compare_digest(
                _signature(previous + data[:-6]), data[-6:]
            ):
                return Verdict.BAD_SIGNATURE
            key = previous
        link_id = data[-13]
        timestamp = int.from_bytes(data[-12:-6], "little")
        stream = (link_id, data[5], data[6])
        last = self._streams.get(stream)
        if last is not None and timestamp <= last:
            return Verdict.REPLAYED
        if last is None and timestamp + NEW_STREAM_SLACK_TICKS < self._clock.current():
            return Verdict.REPLAYED
        self._streams[stream] = timestamp
        self._clock.observe(timestamp)
        self.used = key
        return Verdict.GOOD


class Signer:
    """Signs outgoing frames with one key, one link id and a shared timestamp source."""

    def __init__(self, key: bytes, link_id: int, clock: Timestamps) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a signing key is {KEY_BYTES} bytes")
        self._key = key
        self.link_id = link_id & 0xFF
        self._clock = clock

    @property
    def key(self) -> bytes:
        return self._key

    def use(self, key: bytes) -> None:
        """Sign with ``key`` from now on (the one the peer proved it has)."""
        if len(key) != KEY_BYTES:
            raise ValueError(f"a signing key is {KEY_BYTES} bytes")
        self._key = key

    def sign(self, frame: bytes, key: bytes | None = None) -> bytes:
        """``frame`` signed with the next timestamp, with ``key`` (a peer's, for this frame
        only: threads that sign for different peers never change each other's key) or
        else the key in use."""
        return sign_frame(
            frame, self._key if key is None else key, self.link_id, self._clock.next()
        )
