"""The steering program as built (roost_agent.steering): a program whose jumps are too
long for BPF is refused when built, not when the kernel loads it.

The kernel steering real datagrams is in ``tests/integration/test_agent_steering_kernel.py``.
"""

from __future__ import annotations

import pytest

from roost_agent.steering import (
    COMMAND_ACK,
    HEARTBEAT,
    _assemble,
    _Op,
    urgent_program,
)
from roost_mavlink.codec import Encoder

ENCODER = Encoder(1, 1)
# MAVLink 1: magic, length 9, seq, sysid, compid, id 0, then payload and CRC (not checked
# by the kernel: the link checks every frame after reading it).


@pytest.fixture
def test_a_program_with_jumps_too_long_is_refused_when_built() -> None:
    far = [_Op(0x15, 1, jt="end"), *[_Op(0x04, 1) for _ in range(300)], _Op(0x06, 0, label="end")]
    with pytest.raises(ValueError, match="out of range"):
        _assemble(far)
    with pytest.raises(ValueError, match="below 256"):
        urgent_program([HEARTBEAT, COMMAND_ACK, 300])
