"""The key pod: hands one Vehicle's signing key from its Secret to the agent on its node.

Why a pod of its own: the kubelet's Node authorizer lets a node's kubelet read only the
Secrets that pods bound to that node mount. The agent is a DaemonSet (one pod template
for every node), so a Secret it mounts is readable on every vehicle node. The operator
instead runs this small pod per Vehicle, pinned to the vehicle's node, mounting only
``roost-signing-<vehicle>``; it copies ``key`` and ``previous`` into a host directory
(``/var/lib/roost/signing/<vehicle>/`` by default) that the agent on the same node mounts
read-only, where the agent's :class:`~roost_agent.signing.KeyWatcher` finds them. A
compromised node then exposes its own vehicle's key and no other: its kubelet is refused
every other vehicle's Secret.

The files are written atomically (a temporary file in the same directory, fsync'd,
renamed), mode 0600, owned by the agent's user (``--owner``), in a directory of mode
0700 owned by that user, so the agent never reads half a key and no other user of the
node reads one at all. A Secret update (``roost keys rotate``) reaches the volume within
about a minute; the loop copies it on its next pass, so a rotation reaches the agent
without a restart of either pod. A missing or empty entry is skipped, never written as
an empty key. Nothing here logs or prints key material, only entry names.

``python -m roost_agent.keysync --source /etc/roost/secret --target DIR [--owner UID:GID]``.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading
from collections.abc import Sequence
from pathlib import Path

from roost_agent.signing import KEY_ENTRY, KEY_POLL_S, PREVIOUS_ENTRY

ENTRIES = (KEY_ENTRY, PREVIOUS_ENTRY)
FILE_MODE = 0o600
DIR_MODE = 0o700

log = logging.getLogger("roost_agent.keysync")


def _write_atomically(path: Path, data: bytes, owner: tuple[int, int] | None) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE)  # O_CREAT's mode is masked by the umask
        if owner is not None:
            os.fchown(fd, *owner)
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    tmp.replace(path)


def sync_once(source: Path, target: Path, owner: tuple[int, int] | None = None) -> list[str]:
    """Copy the Secret's ``key`` and ``previous`` from ``source`` to ``target``.

    Returns the names of the entries written (those that differed). An entry missing or
    empty in the Secret leaves the target's file alone: an agent keeps its key rather
    than lose signing to a Secret caught mid-update.
    """
    target.mkdir(parents=True, exist_ok=True)
    target.chmod(DIR_MODE)
    if owner is not None:
        os.chown(target, *owner)
    written: list[str] = []
    for entry in ENTRIES:
        try:
            data = (source / entry).read_bytes()
        except FileNotFoundError:
            continue
        if not data.strip():
            continue
        dest = target / entry
        try:
            same = dest.read_bytes() == data
        except FileNotFoundError:
            same = False
        if not same:
            _write_atomically(dest, data, owner)
            written.append(entry)
    return written


def parse_owner(text: str) -> tuple[int, int]:
    """``UID:GID`` (or ``UID``, group the same) as numbers."""
    uid, _, gid = text.partition(":")
    try:
        return int(uid), int(gid or uid)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--owner {text!r}: expected UID:GID") from None


def run(
    source: Path,
    target: Path,
    owner: tuple[int, int] | None,
    stop: threading.Event,
    every_s: float = KEY_POLL_S,
) -> None:
    """Sync now and then every ``every_s`` until ``stop``; a failed pass is logged once
    per distinct error (never with key material) and retried on the next."""
    problem: str | None = None
    while True:
        try:
            written = sync_once(source, target, owner)
        except OSError as exc:
            text = f"{exc.filename}: {exc.strerror}"
            if text != problem:
                log.warning("cannot hand the signing key over: %s", text)
            problem = text
        else:
            problem = None
            if written:
                log.info("signing key entries updated in %s: %s", target, ", ".join(written))
        if stop.wait(every_s):
            return


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roost-agent-keysync", description=__doc__)
    parser.add_argument("--source", type=Path, required=True, help="the mounted Secret")
    parser.add_argument("--target", type=Path, required=True, help="the host directory")
    parser.add_argument("--owner", type=parse_owner, default=None, help="UID:GID of files")
    parser.add_argument("--every", type=float, default=KEY_POLL_S, help="seconds per pass")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    run(args.source, args.target, args.owner, stop, args.every)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
