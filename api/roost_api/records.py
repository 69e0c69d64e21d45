"""What the flight records' producers and readers agree on beyond the manifest's shape.

A flight record's files are named in manifests by their SHA-256 (the agent writes it, the
operator checks each file it gathers against it and records its own in a Mission's
bundle, ``roost records get`` checks what it downloads): one digest function, so the
three can never disagree on how a file is read.
"""

from __future__ import annotations

from pathlib import Path


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
