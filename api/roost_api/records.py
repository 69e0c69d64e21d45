"""What the flight records' producers and readers agree on: a flight's and a file's states
and kinds as the agent's ``flight.json`` names them, and how a file is digested.

A flight record's files are named in manifests by their SHA-256 (the agent writes it, the
operator checks each file it gathers against it and records its own in a Mission's
bundle, ``roost records get`` checks what it downloads): one digest function, so the
three can never disagree on how a file is read.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path


class FlightState(StrEnum):
    RECORDING = "Recording"  # armed: the recorder writes
    LANDED = "Landed"  # disarmed everywhere: the autopilots' logs are being fetched
    COMPLETE = "Complete"  # everything written and fetched
    FAILED = "Failed"  # something could not be recorded (the message says what)


class FileState(StrEnum):
    PARTIAL = "Partial"
    COMPLETE = "Complete"
    FAILED = "Failed"


class FileKind(StrEnum):
    TLOG = "tlog"
    DECISIONS = "decisions"
    PARAMS = "params"
    AUTOPILOT_LOG = "autopilot-log"


def sha256_of(path: Path) -> str:
    """The hex SHA-256 of a file, read in 1 MiB blocks (records are tens of MB)."""
    # hashlib maps libcrypto: only a process that hashes records pays for it (the agent
    # imports its records modules for its flags' defaults).
    import hashlib  # noqa: PLC0415

    digest = hashlib.sha256()
    with path.open("rb") as data:
        for block in iter(lambda: data.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
