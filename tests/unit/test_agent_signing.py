"""Key rotation as pure rules: which key files count, what a watcher hands on, which key
a verifier accepted (no sockets)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from roost_agent.signing import (
    KeyWatcher,
    LinkSigning,
    SigningError,
    SigningMode,
    load_signing,
    read_keys,
)
from roost_mavlink.codec import Encoder
from roost_mavlink.signing import Signer, Timestamps, Verdict, Verifier

OLD = bytes(range(32))
NEW = bytes(range(32, 64))
OTHER = bytes(range(64, 96))


def heartbeat() -> bytes:
    return Encoder(1, 1).encode(
        "HEARTBEAT", type=2, autopilot=12, base_mode=0, custom_mode=0, system_status=4,
        mavlink_version=3,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("signed_with", "verdict", "used"),
    [(NEW, Verdict.GOOD, NEW), (OLD, Verdict.GOOD, OLD), (OTHER, Verdict.BAD_SIGNATURE, None)],
)
def test_a_verifier_takes_the_current_and_the_previous_key(
    signed_with: bytes, verdict: Verdict, used: bytes | None
) -> None:
    clock = Timestamps()
    verifier = Verifier(NEW, clock, previous=OLD)
    frame = Signer(signed_with, 1, Timestamps()).sign(heartbeat())
    assert verifier.check(frame) is verdict
    if used is not None:
        assert verifier.used == used


def test_a_signer_signs_with_the_key_it_is_told_to_use() -> None:
    signer = Signer(NEW, 1, Timestamps())
    signer.use(OLD)
    assert Verifier(OLD, Timestamps()).check(signer.sign(heartbeat())) is Verdict.GOOD


def test_a_frame_signed_for_one_peer_leaves_the_key_in_use_alone() -> None:
    """The hub signs for clients with different keys from two threads: a key given for
    one frame must not become the key another thread signs with."""
    signer = Signer(NEW, 1, Timestamps())
    for_old = signer.sign(heartbeat(), OLD)
    assert signer.key == NEW
    assert Verifier(OLD, Timestamps()).check(for_old) is Verdict.GOOD
    assert Verifier(NEW, Timestamps()).check(signer.sign(heartbeat())) is Verdict.GOOD


def write(path: Path, key: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(key.hex() + "\n")


KEY_LAYOUTS = [
    # files under the key directory, (key, previous) read or None
    ({}, None),
    ({"drone-1": NEW}, (NEW, None)),  # one file per Vehicle (a fleet Secret)
    ({"drone-1/key": NEW}, (NEW, None)),  # a per-Vehicle Secret's entries
    ({"drone-1/key": NEW, "drone-1/previous": OLD}, (NEW, OLD)),
    ({"drone-2/key": NEW}, None),  # another vehicle's key is not ours
]


@pytest.mark.parametrize(("files", "expected"), KEY_LAYOUTS)
def test_read_keys(
    tmp_path: Path, files: dict[str, bytes], expected: tuple[bytes, bytes | None] | None
) -> None:
    for name, key in files.items():
        write(tmp_path / name, key)
    assert read_keys(tmp_path, "drone-1") == expected


def test_a_malformed_key_is_refused_without_quoting_it(tmp_path: Path) -> None:
    (tmp_path / "drone-1").mkdir()
    (tmp_path / "drone-1" / "key").write_text("zz" + NEW.hex()[2:])
    with pytest.raises(SigningError) as err:
        read_keys(tmp_path, "drone-1")
    assert NEW.hex()[2:10] not in str(err.value)


def test_the_watcher_hands_on_a_rotated_key_once_and_keeps_the_key_on_a_bad_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    write(tmp_path / "drone-1" / "key", OLD)
    signing = load_signing(SigningMode.REQUIRE, tmp_path, "drone-1", tmp_path / "state")
    assert signing is not None
    got: list[LinkSigning] = []
    watcher = KeyWatcher(tmp_path, "drone-1", signing, got.append)
    assert watcher.check() is False  # nothing changed
    write(tmp_path / "drone-1" / "key", NEW)
    write(tmp_path / "drone-1" / "previous", OLD)
    assert watcher.check() is True
    assert watcher.check() is False
    assert [(s.key, s.previous, s.require) for s in got] == [(NEW, OLD, True)]
    assert got[0].clock is signing.clock  # timestamps keep increasing across the rotation
    (tmp_path / "drone-1" / "key").write_text("half-written")
    assert watcher.check() is False
    assert watcher.current.key == NEW
    (tmp_path / "drone-1" / "key").unlink()  # the Secret gone: keep signing, never drop it
    assert watcher.check() is False
    for key in (OLD, NEW):
        assert key.hex() not in caplog.text and key.hex()[:16] not in caplog.text
