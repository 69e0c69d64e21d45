"""Local ports for programs started later: picked where nothing else is handed them.

Tests, benchmarks and the sandbox start programs (an agent, etcd, a relay) that must
listen on a port known in advance. The old way, binding port 0, reading the number and
closing the socket, races: that number comes from the kernel's ephemeral range, and
between the close and the program's own bind the kernel can give it to any other socket
(another pytest-xdist worker's bind to 0, or an unbound UDP or TCP socket that sends or
connects: autobind), and the program dies with "Address already in use". The kernel
never gives out a port below its ephemeral range by itself (Linux reads the range from
``/proc/sys/net/ipv4/ip_local_port_range``), so :func:`free_port` picks there, and so
that two processes calling it do not pick the same port, each takes its ports from a
block of its own:

- a pytest-xdist worker (``PYTEST_XDIST_WORKER=gwN``) from the region of worker N, which
  no other worker of the run shares (``PYTEST_XDIST_WORKER_COUNT`` divides the space);
  the block inside the region by pid, because a program the worker starts inherits the
  worker's variables and may pick ports too;
- any other process (a benchmark, the sandbox, an agent, ``roost-cluster up``) from a
  region of its own, the block by pid.

Inside its block a process hands out the ports in turn (a counter, wrapping), starting at
an offset derived from its pid, skipping the ports :data:`RESERVED` lists and every port
it cannot bind now (a fixed listener, a port still held).

Limits: blocks chosen by pid are distinct only probably: two processes of one region
whose pids agree modulo the region's block count share a block (then only their starts
in it differ), and two pytest runs side by side (two checkouts) give their worker N the
same region. The binding check leaves only a port that two such processes pick while
neither has bound it yet. A process that picks more ports than its block holds before
their programs bind them gets one twice. Without room below the ephemeral range
(:data:`PORT_FLOOR` plus a few blocks) the kernel picks the port, with the old race.
"""

from __future__ import annotations

import errno
import functools
import os
import socket
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

from roost_api.sitl import (
    ARDUPILOT_TCP_PORT_BASE,
    ARDUPILOT_TCP_PORT_STEP,
    MAX_SITL_INSTANCES,
    PX4_API_PORT_BASE,
    PX4_LOCAL_PORT_BASE,
)

LOOPBACK = "127.0.0.1"
PORT_FLOOR = 1024
"""Below it the well-known ports (and binding needs privileges)."""
BLOCK_SIZE = 256
"""Ports in one process's block: more than a test or a benchmark picks before
its programs bind them."""
MIN_BLOCKS = 4
"""Fewer blocks than this below the ephemeral range: the kernel picks (see the limits)."""
ASSUMED_WORKERS = 8
"""How many regions the workers' space is cut into when xdist does not say its count."""
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
DEFAULT_EPHEMERAL = (32768, 65535)
"""Where the file is absent: from Linux's default start (IANA's, 49152, is higher) up."""
RESERVED: tuple[range, ...] = (
    range(2379, 2381),  # etcd's default client and peer ports
    # ArduPilot SITL's TCP serial ports (roost_api.sitl)
    range(
        ARDUPILOT_TCP_PORT_BASE,
        ARDUPILOT_TCP_PORT_BASE + ARDUPILOT_TCP_PORT_STEP * MAX_SITL_INSTANCES,
    ),
    range(6443, 6444),  # a K3s or KinD API server
    range(8080, 8081),  # the operator's health endpoint (the chart's healthPort)
    range(8765, 8766),  # roost dashboard
    # agent metrics 9465, operator metrics 9466, agent telemetry 9467, agent records
    # 9468, operator records 9469
    range(9465, 9470),
    range(10248, 10260),  # kubelet, kube-proxy, controller-manager and scheduler defaults
    # PX4 SITL's API and local ports (roost_api.sitl), a ground station's 14550 among them
    range(PX4_API_PORT_BASE, PX4_LOCAL_PORT_BASE + MAX_SITL_INSTANCES),
    range(24550, 24650),  # the sandbox's agent hubs (roost_cli.sandbox.plan.HUB_PORT_BASE up)
)
"""Ports Roost or the programs it runs beside use on fixed numbers: never picked."""


def reserved(port: int) -> bool:
    """Whether ``port`` is one of :data:`RESERVED`."""
    return any(port in ports for ports in RESERVED)


def ephemeral_range(path: Path = EPHEMERAL_RANGE_FILE) -> tuple[int, int]:
    """The first and last port the kernel hands out by itself (:data:`DEFAULT_EPHEMERAL`
    when ``path`` cannot be read)."""
    try:
        low, high = (int(part) for part in path.read_text().split())
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL
    return low, high


def port_block(
    pid: int,
    worker: str | None = None,
    workers: int | None = None,
    ephemeral_low: int = DEFAULT_EPHEMERAL[0],
) -> Sequence[int] | None:
    """The block of process ``pid``: xdist worker ``worker`` (``gwN``) of ``workers``, or
    no worker (None, or a name that is not ``gwN``). None without room below
    ``ephemeral_low``.

    The ports from :data:`PORT_FLOOR` to ``ephemeral_low`` but the :data:`RESERVED` ones
    are cut into blocks (so that no block is all reserved: ArduPilot SITL's 400 would
    cover one whole); a quarter of them is the region of processes that are no worker,
    the rest is cut into one region per worker (when there are more workers than
    blocks, workers share).
    """
    space = _candidates(ephemeral_low)
    blocks = len(space) // BLOCK_SIZE
    if blocks < MIN_BLOCKS:
        return None
    shared = blocks // 4
    index = _worker_index(worker)
    if index is None:
        block = pid % shared
    else:
        per_worker = max(1, (blocks - shared) // (workers or ASSUMED_WORKERS))
        regions = (blocks - shared) // per_worker
        block = shared + (index % regions) * per_worker + pid % per_worker
    return space[block * BLOCK_SIZE : (block + 1) * BLOCK_SIZE]


@functools.cache
def _candidates(ephemeral_low: int) -> tuple[int, ...]:
    """The ports blocks are cut from: below ``ephemeral_low``, none reserved."""
    return tuple(port for port in range(PORT_FLOOR, ephemeral_low) if not reserved(port))


def _worker_index(worker: str | None) -> int | None:
    if worker is None or not worker.startswith("gw") or not worker[2:].isdigit():
        return None
    return int(worker[2:])


class PortPicker:
    """Hands out the ports of one block in turn from ``start`` (an offset in it),
    wrapping, skipping reserved ports and those ``is_free`` refuses."""

    def __init__(self, block: Sequence[int], start: int = 0) -> None:
        self.block = block
        self._next = start

    def pick(self, is_free: Callable[[int], bool]) -> int:
        for _ in range(len(self.block)):
            port = self.block[self._next % len(self.block)]
            self._next += 1
            if not reserved(port) and is_free(port):
                return port
        raise OSError(errno.EADDRINUSE, f"no free port in {self.block[0]}-{self.block[-1]}")


def port_free(
    port: int, kind: socket.SocketKind = socket.SOCK_STREAM, host: str = LOOPBACK
) -> bool:
    """Whether ``host``:``port`` can be bound now for ``kind`` (TCP or UDP)."""
    with socket.socket(socket.AF_INET, kind) as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


class _ProcessPorts:
    """This process's picker (None: no room for blocks), made at its first pick; a
    forked child makes its own."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self._pid: int | None = None
        self._picker: PortPicker | None = None

    def picker(self) -> PortPicker | None:
        pid = os.getpid()
        if self._pid != pid:
            workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT", "")
            block = port_block(
                pid,
                os.environ.get("PYTEST_XDIST_WORKER"),
                int(workers) if workers.isdigit() else None,
                ephemeral_range()[0],
            )
            self._pid = pid
            self._picker = None if block is None else PortPicker(block, pid % BLOCK_SIZE)
        return self._picker


_PROCESS = _ProcessPorts()


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM, host: str = LOOPBACK) -> int:
    """A port of ``host`` that a program this process starts can bind for ``kind`` (TCP
    or UDP) later: free now, below the kernel's ephemeral range, and from this process's
    own block, so no other caller of this function is handed it (the limits are in the
    module's docstring). Consecutive calls return different ports."""
    with _PROCESS.lock:
        picker = _PROCESS.picker()
        if picker is not None:
            return picker.pick(lambda port: port_free(port, kind, host))
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])
