"""The key pod's hand-over (``roost_agent.keysync``): the vehicle's Secret copied where the
agent on the node reads it, on real files in a temporary directory."""

from __future__ import annotations

import stat
import threading
from pathlib import Path

import pytest

from roost_agent.keysync import parse_owner, run, sync_once
from roost_agent.signing import KeyWatcher, LinkSigning, read_keys
from roost_mavlink.signing import Timestamps

KEY_A = "aa" * 32
KEY_B = "bb" * 32


def secret_dir(tmp_path: Path, key: str, previous: str = "") -> Path:
    source = tmp_path / "secret"
    source.mkdir(exist_ok=True)
    (source / "key").write_text(key)
    (source / "previous").write_text(previous)
    return source


def test_sync_writes_the_key_mode_0600_in_a_0700_directory_the_agent_reads(
    tmp_path: Path,
) -> None:
    source = secret_dir(tmp_path, KEY_A)
    target = tmp_path / "host" / "d1"
    assert sync_once(source, target) == ["key"]  # an empty previous is not written
    assert stat.S_IMODE((target / "key").stat().st_mode) == 0o600
    assert stat.S_IMODE(target.stat().st_mode) == 0o700
    assert not (target / "previous").exists()
    assert read_keys(tmp_path / "host", "d1") == (bytes.fromhex(KEY_A), None)
    assert sync_once(source, target) == []  # nothing changed, nothing written


def test_a_rotation_reaches_the_agents_key_watcher(tmp_path: Path) -> None:
    source = secret_dir(tmp_path, KEY_A)
    host = tmp_path / "host"
    sync_once(source, host / "d1")
    current = LinkSigning(key=bytes.fromhex(KEY_A), require=True, clock=Timestamps())
    rotated: list[LinkSigning] = []
    watcher = KeyWatcher(host, "d1", current, rotated.append)
    secret_dir(tmp_path, KEY_B, previous=KEY_A)  # roost keys rotate
    assert sorted(sync_once(source, host / "d1")) == ["key", "previous"]
    assert watcher.check()
    assert (rotated[0].key, rotated[0].previous) == (bytes.fromhex(KEY_B), bytes.fromhex(KEY_A))


def test_an_entry_missing_from_the_secret_keeps_the_handed_key(tmp_path: Path) -> None:
    source = secret_dir(tmp_path, KEY_A)
    target = tmp_path / "host" / "d1"
    sync_once(source, target)
    (source / "key").write_text("")
    assert sync_once(source, target) == []
    assert (target / "key").read_text() == KEY_A


def test_the_loop_syncs_until_stopped_and_never_logs_the_key(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    source = secret_dir(tmp_path, KEY_A, previous=KEY_B)
    target = tmp_path / "host" / "d1"
    stop = threading.Event()
    stop.set()  # one pass, then stop
    with caplog.at_level("DEBUG"):
        run(source, target, None, stop, every_s=0.01)
    assert (target / "key").read_text() == KEY_A
    assert KEY_A not in caplog.text and KEY_B not in caplog.text
    assert "key" in caplog.text


def test_a_failed_pass_is_reported_once_without_key_material(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    source = secret_dir(tmp_path, KEY_A)
    blocker = tmp_path / "host"
    blocker.write_text("not a directory")
    stop = threading.Event()
    stop.set()
    with caplog.at_level("WARNING"):
        run(source, blocker / "d1", None, stop, every_s=0.01)
    assert "cannot hand the signing key over" in caplog.text
    assert KEY_A not in caplog.text


@pytest.mark.parametrize(
    ("text", "owner"), [("65532:65532", (65532, 65532)), ("1000", (1000, 1000))]
)
def test_owner_parses(text: str, owner: tuple[int, int]) -> None:
    assert parse_owner(text) == owner
