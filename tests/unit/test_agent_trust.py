"""Who a link believes, as pure rules: the source lock, MAVLink signing, connection URLs;
and the link's plumbing: the ack mailbox, the kernel stamps' clock offset."""

from __future__ import annotations

import os
import time

os.environ.setdefault("MAVLINK20", "1")

from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from roost_agent import transport
from roost_agent.link import AckMailbox
from roost_agent.signing import (
    RESERVE_TICKS,
    SIGNING_TIMESTAMP_FILE,
    PersistentTimestamps,
    SigningError,
    SigningMode,
    load_signing,
)
from roost_agent.spec_changes import connection_problems
from roost_agent.trust import SourceLock
from roost_api.autopilot import AutopilotSpec, RedundantAutopilotSpec
from roost_mavlink import pymavlink_device
from roost_mavlink.signing import (
    NEW_STREAM_SLACK_TICKS,
    Signer,
    Timestamps,
    Verdict,
    Verifier,
    split_frames,
)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
AP: tuple[str, int] = ("127.0.0.1", 14580)
SPOOF: tuple[str, int] = ("127.0.0.1", 40000)
NEW_PORT: tuple[str, int] = ("127.0.0.1", 14581)


# -- the source lock: decision table -------------------------------------------------------


def test_first_address_with_two_heartbeats_takes_the_lock() -> None:
    lock = SourceLock(relock_after_s=3.0)
    assert lock.hears(SPOOF, 0.0) and lock.hears(AP, 0.0)  # nobody proved itself yet
    assert lock.prove(AP, 0.0) is False  # one heartbeat is not a stream
    assert lock.prove(AP, 1.0) is True
    assert lock.locked == AP
    assert not lock.hears(SPOOF, 1.1)


def test_heartbeats_too_far_apart_do_not_prove_anything() -> None:
    lock = SourceLock(relock_after_s=3.0)
    lock.prove(AP, 0.0)
    assert lock.prove(AP, 5.0) is False  # the count starts over
    assert lock.prove(AP, 6.0) is True


def test_relock_only_after_the_locked_address_fell_silent() -> None:
    """The autopilot (locked at t=1) reboots onto another port and sends from there every
    0.5 s: nothing from the new port counts until the old one has been silent for the
    relock time (3 s, t=4), then two heartbeats prove it (t=4.5)."""
    lock = SourceLock(relock_after_s=3.0)
    lock.prove(AP, 0.0)
    lock.prove(AP, 1.0)
    lock.seen(1.0)
    took = [t / 2 for t in range(3, 20) if lock.prove(NEW_PORT, t / 2)]
    assert took == [4.5] and lock.locked == NEW_PORT
    assert not lock.hears(AP, 4.6)  # the old port is foreign now


def test_a_live_autopilot_keeps_its_lock_against_a_steady_spoofer() -> None:
    lock = SourceLock(relock_after_s=3.0)
    lock.prove(AP, 0.0)
    lock.prove(AP, 1.0)
    for i in range(100):
        t = 1.0 + i * 0.1
        lock.seen(t)
        assert lock.prove(SPOOF, t) is False
    assert lock.locked == AP


def test_a_fixed_peer_never_moves() -> None:
    lock = SourceLock(relock_after_s=3.0, fixed=AP)
    assert lock.locked == AP and not lock.hears(SPOOF, 0.0)
    assert lock.prove(SPOOF, 100.0) is False and lock.prove(SPOOF, 101.0) is False
    assert lock.locked == AP


def test_a_configured_host_hears_any_port_of_that_host_only() -> None:
    lock = SourceLock(relock_after_s=3.0, host="127.0.0.2")
    assert not lock.hears(AP, 0.0)
    assert lock.prove(("127.0.0.2", 5), 0.0) is False
    assert lock.prove(("127.0.0.2", 5), 1.0) is True


def test_candidates_are_bounded() -> None:
    lock = SourceLock(relock_after_s=3.0)
    for port in range(1, 1000):
        lock.prove(("127.0.0.1", port), 0.0)
    assert lock.prove(("127.0.0.1", 999), 0.5) is True  # the newest candidate is remembered
    assert len(lock._candidates) == 0


# -- signing ---------------------------------------------------------------------------------


def _frame(sysid: int = 1, boot_ms: int = 1000) -> bytes:
    sender = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
    return bytes(sender.attitude_encode(boot_ms, 0, 0, 0, 0, 0, 0).pack(sender))


def test_our_signature_is_accepted_by_pymavlink_itself() -> None:
    """Interoperability: pymavlink (what MAVProxy and many tools use) checks our frames."""
    signed = Signer(KEY, 3, Timestamps()).sign(_frame())
    receiver = mav.MAVLink(None)
    receiver.signing.secret_key = KEY
    receiver.signing.allow_unsigned_callback = lambda *_: False
    msg = receiver.decode(bytearray(signed))
    assert msg.get_type() == "ATTITUDE" and msg._signed and msg._link_id == 3
    assert receiver.signing.goodsig_count == 1


def test_pymavlink_signed_frames_pass_our_verifier() -> None:
    sender = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    sender.signing.secret_key = KEY
    sender.signing.sign_outgoing = True
    sender.signing.timestamp = Timestamps().next()
    frame = bytes(sender.heartbeat_encode(2, 12, 0, 0, 4).pack(sender))
    assert Verifier(KEY, Timestamps()).check(frame) is Verdict.GOOD


def test_verifier_verdicts() -> None:
    clock = Timestamps()
    verifier = Verifier(KEY, clock)
    signer = Signer(KEY, 0, Timestamps())
    first, second = signer.sign(_frame()), signer.sign(_frame())
    assert verifier.check(_frame()) is Verdict.UNSIGNED
    assert (
        verifier.check(Signer(OTHER_KEY, 0, Timestamps()).sign(_frame())) is Verdict.BAD_SIGNATURE
    )
    tampered = bytearray(first)
    tampered[14] ^= 0x01  # one payload bit
    assert verifier.check(bytes(tampered)) is Verdict.BAD_SIGNATURE
    assert verifier.check(second) is Verdict.GOOD
    assert verifier.check(first) is Verdict.REPLAYED  # older than the stream's last
    assert verifier.check(second) is Verdict.REPLAYED  # the same frame again


def test_a_forged_future_timestamp_does_not_poison_the_stream() -> None:
    verifier = Verifier(KEY, Timestamps())
    real = Signer(KEY, 0, Timestamps())
    forged = Signer(OTHER_KEY, 0, Timestamps(start=2**47))
    assert verifier.check(forged.sign(_frame())) is Verdict.BAD_SIGNATURE
    assert verifier.check(real.sign(_frame())) is Verdict.GOOD


def test_a_new_stream_more_than_a_minute_old_is_a_replay() -> None:
    now = Timestamps()
    old = Signer(
        KEY, 0, Timestamps(wall=lambda: 0.0, start=now.current() - 2 * NEW_STREAM_SLACK_TICKS)
    )
    assert Verifier(KEY, now).check(old.sign(_frame())) is Verdict.REPLAYED


def test_split_frames_skips_noise_and_keeps_whole_frames() -> None:
    a, b = _frame(boot_ms=1), Signer(KEY, 0, Timestamps()).sign(_frame(boot_ms=2))
    assert split_frames(b"\x00junk" + a + b"\x01\x02" + b + a[:5]) == [a, b]


def test_timestamps_survive_a_restart_even_with_a_clock_reset(tmp_path: Path) -> None:
    path = tmp_path / SIGNING_TIMESTAMP_FILE
    first = PersistentTimestamps(path)
    issued = [first.next() for _ in range(100)]
    assert issued == sorted(set(issued))
    assert first.reserved >= issued[-1] and path.exists()
    # The companion computer reboots without a real-time clock: the wall says 1970.
    again = PersistentTimestamps(path, wall=lambda: 0.0)
    assert again.next() > issued[-1]
    assert again.reserved <= issued[-1] + 2 * RESERVE_TICKS


def test_signing_setup_and_its_refusals_never_show_the_key(tmp_path: Path) -> None:
    keys, state = tmp_path / "keys", tmp_path / "state"
    keys.mkdir()
    assert load_signing(SigningMode.AUTO, keys, "drone-1", state) is None
    with pytest.raises(SigningError, match="no key for vehicle 'drone-1'"):
        load_signing(SigningMode.REQUIRE, keys, "drone-1", state)
    secret = "zz" + KEY.hex()[2:]
    (keys / "drone-1").write_text(secret)
    with pytest.raises(SigningError) as refused:
        load_signing(SigningMode.AUTO, keys, "drone-1", state)
    assert secret not in str(refused.value) and KEY.hex()[2:10] not in str(refused.value)
    (keys / "drone-1").write_text(KEY.hex() + "\n")
    signing = load_signing(SigningMode.AUTO, keys, "drone-1", state)
    assert signing is not None and signing.require and signing.key == KEY
    assert KEY.hex() not in repr(signing) and str(KEY) not in repr(signing)
    sign_only = load_signing(SigningMode.SIGN, keys, "drone-1", state)
    assert sign_only is not None and not sign_only.require
    assert load_signing(SigningMode.OFF, keys, "drone-1", state) is None


# -- connection URLs ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "why"),
    [
        ("udp://127.0.0.1:0", "port 0 is not 1-65535"),
        ("udp://127.0.0.1:70000", "port 70000 is not 1-65535"),
        ("udpout://:14550", "lacks a host"),
        ("tcp://:5760", "lacks a host"),
        ("tcp://127.0.0.1", "lacks a port"),
        ("udp://127.0.0.1:abc", "port abc is not 1-65535"),
        ("serial:///tmp/tty:57600", "a path under /dev/"),
        ("serial://ttyUSB0:57600", "a path under /dev/"),
        ("serial:///dev/ttyUSB0:fast", "baud 'fast' is not a positive number"),
        ("serial:///dev/ttyUSB0:0", "baud '0' is not a positive number"),
        ("udpout://10.0.0.2:14550@10.0.0.3", "only udp:// takes an @peer"),
        ("udp://0.0.0.0:14540@", "bad @peer"),
        ("udp://0.0.0.0:14540@10.0.0.3:99999", "port 99999 is not 1-65535"),
    ],
)
def test_connection_urls_the_agent_could_not_open_are_refused(url: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        pymavlink_device(url)


def test_a_udp_listener_may_name_its_autopilot() -> None:
    exact = pymavlink_device("udp://0.0.0.0:14540@127.0.0.1:14580")
    assert (exact.device, exact.peer) == ("udpin:0.0.0.0:14540", ("127.0.0.1", 14580))
    host_only = pymavlink_device("udp://0.0.0.0:14540@10.0.0.3")
    assert host_only.peer == ("10.0.0.3", None)


def test_a_spec_with_a_connection_the_agent_could_not_open_is_named_per_autopilot() -> None:
    spec = RedundantAutopilotSpec(
        vehicle_name="v1",
        autopilots=[
            AutopilotSpec(
                name="fc1",
                stack="px4",
                connection="udp://127.0.0.1:70000",
                sysid=1,
                bridge_channel=0,
            ),
            AutopilotSpec(
                name="fc2",
                stack="px4",
                connection="udp://127.0.0.1:14541",
                sysid=2,
                bridge_channel=1,
            ),
        ],
        primary="fc1",
    )
    assert connection_problems(spec) == [
        "autopilot fc1: connection 'udp://127.0.0.1:70000': port 70000 is not 1-65535"
    ]


# -- link plumbing ---------------------------------------------------------------------


def test_ack_mailbox_returns_only_acks_newer_than_the_request() -> None:
    box = AckMailbox()
    box.put(176, 1)
    serial = box.serial(176)
    assert box.wait(176, serial, 0.01) is None  # the old ack does not answer a new request
    box.put(176, 0)
    assert box.wait(176, serial, 0.01) == 0


def test_the_realtime_offset_matches_the_clocks() -> None:
    """Turning a kernel stamp (realtime) into the agent's clock (monotonic)."""
    offset = transport.realtime_offset()
    assert abs((time.time() - time.monotonic()) - offset) < 0.05
