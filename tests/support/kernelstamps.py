"""Waiting for the kernel to stamp datagrams on arrival (``SO_TIMESTAMPNS``).

Tests that compare arrival stamps (how late a datagram was read, the order of two
sockets' datagrams) must not start before the kernel's global switch is on.
"""

from __future__ import annotations

import socket
import struct
import time

from roost_agent.transport import SO_TIMESTAMPNS


def until_the_kernel_stamps_arrivals(timeout_s: float = 5.0) -> None:
    """Linux turns arrival stamping on (a global switch) a little after the first socket
    asks for SO_TIMESTAMPNS; until then a datagram is stamped when it is read. Wait until
    a probe datagram read 20 ms after it was sent carries the earlier time."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        probe.bind(("127.0.0.1", 0))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            probe.sendto(b"probe", probe.getsockname())
            time.sleep(0.02)
            _, ancillary, _, _ = probe.recvmsg(64, 64)
            read_at = time.time()
            stamps = [
                seconds + nanoseconds * 1e-9
                for level, kind, value in ancillary
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS
                for seconds, nanoseconds in [struct.unpack("qq", value[:16])]
            ]
            if stamps and read_at - stamps[0] > 0.01:
                return
    raise AssertionError("the kernel never stamped a datagram on arrival")
