"""Ports for programs started later: below the ephemeral range, one block per process.

The layout and the picking are pure (an injected probe stands for binding); the real
binding is checked in tests/integration/test_api_ports_sockets.py.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from roost_agent import metrics as agent_metrics
from roost_agent import records as agent_records
from roost_api import ports
from roost_api.meta import Stack
from roost_api.sitl import MAX_SITL_INSTANCES, sitl_endpoint
from roost_cli import records as cli_records
from roost_cli.dashboard import server as dashboard
from roost_cli.sandbox import plan
from roost_operator import metrics as operator_metrics

PIDS = st.integers(min_value=1, max_value=4_194_304)
LOWS = st.integers(min_value=ports.PORT_FLOOR, max_value=65535)


@given(
    pid=PIDS,
    worker=st.none() | st.integers(0, 63).map(lambda n: f"gw{n}"),
    workers=st.none() | st.integers(1, 64),
    low=LOWS,
)
def test_a_block_lies_between_the_well_known_ports_and_the_ephemeral_range(
    pid: int, worker: str | None, workers: int | None, low: int
) -> None:
    block = ports.port_block(pid, worker, workers, low)
    if block is None:
        assert low < ports.PORT_FLOOR + ports.MIN_BLOCKS * ports.BLOCK_SIZE
        return
    assert len(block) == ports.BLOCK_SIZE
    assert min(block) >= ports.PORT_FLOOR and max(block) < low
    assert not any(ports.reserved(port) for port in block)


def test_this_machines_blocks_lie_below_its_ephemeral_range() -> None:
    low, high = ports.ephemeral_range()
    assert ports.PORT_FLOOR < low <= high
    for worker in (None, "gw0", "gw1"):
        block = ports.port_block(os.getpid(), worker, 2, low)
        assert block is not None and min(block) >= ports.PORT_FLOOR and max(block) < low


@given(
    pids=st.tuples(PIDS, PIDS),
    pair=st.integers(1, 16).flatmap(
        lambda n: st.tuples(st.just(n), st.integers(0, n - 1), st.integers(0, n - 1))
    ),
    low=st.sampled_from([10000, 32768, 49152]),
)
def test_two_workers_of_a_run_never_share_a_port_whatever_their_pids(
    pids: tuple[int, int], pair: tuple[int, int, int], low: int
) -> None:
    workers, one, other = pair
    first = ports.port_block(pids[0], f"gw{one}", workers, low)
    second = ports.port_block(pids[1], f"gw{other}", workers, low)
    outsider = ports.port_block(pids[1], None, None, low)
    assert first is not None and second is not None and outsider is not None
    assert not set(first) & set(outsider)
    if one != other:
        assert not set(first) & set(second)


def test_no_block_is_all_reserved_ports() -> None:
    """ArduPilot SITL's reserved ports span more than a block: a process whose block fell
    there once had no port to pick at all."""
    low = ports.DEFAULT_EPHEMERAL[0]
    for pid in range(0, 4096, 7):
        block = ports.port_block(pid, None, None, low)
        assert block is not None and not any(ports.reserved(port) for port in block)


def test_a_worker_and_the_programs_it_starts_get_blocks_by_pid() -> None:
    """A program a worker starts inherits PYTEST_XDIST_WORKER: the pid tells them apart."""
    worker = ports.port_block(1000, "gw0", 2)
    child = ports.port_block(1001, "gw0", 2)
    assert worker is not None and child is not None and worker != child


def test_a_name_that_is_no_worker_gets_a_block_of_the_other_processes() -> None:
    assert ports.port_block(7, "main") == ports.port_block(7, None)


def test_consecutive_picks_differ_and_wrap_inside_the_block() -> None:
    picker = ports.PortPicker(range(20000, 20004), start=2)
    picked = [picker.pick(lambda _: True) for _ in range(6)]
    assert picked == [20002, 20003, 20000, 20001, 20002, 20003]


def test_a_taken_port_and_the_reserved_ones_are_skipped() -> None:
    taken = {20001}
    picker = ports.PortPicker(range(20000, 20003))
    assert [picker.pick(lambda port: port not in taken) for _ in range(3)] == [
        20000,
        20002,
        20000,
    ]
    around_metrics = ports.PortPicker(range(9463, 9472))
    assert [around_metrics.pick(lambda _: True) for _ in range(4)] == [9463, 9464, 9470, 9471]


def test_a_block_with_nothing_free_is_an_error() -> None:
    picker = ports.PortPicker(range(20000, 20003))
    with pytest.raises(OSError, match="no free port in 20000-20002"):
        picker.pick(lambda _: False)


def test_the_projects_fixed_ports_are_reserved() -> None:
    fixed = [
        agent_metrics.DEFAULT_PORT,
        agent_records.DEFAULT_PORT,
        operator_metrics.DEFAULT_PORT,
        cli_records.RECORDS_PORT,
        dashboard.DEFAULT_PORT,
        14550,  # a ground station
        *range(plan.HUB_PORT_BASE, plan.HUB_PORT_BASE + plan.MAX_VEHICLES),
    ]
    for instance in range(MAX_SITL_INSTANCES):
        for stack in Stack:
            endpoint = sitl_endpoint(instance, 0, stack, slots_per_vehicle=1)
            fixed += [endpoint.agent_port, endpoint.autopilot_port]
        fixed += [sitl_endpoint(instance, 0, Stack.ARDUPILOT, 1).autopilot_port + 3]
    assert [port for port in fixed if not ports.reserved(port)] == []


def test_the_ephemeral_range_is_read_from_the_kernels_file(tmp_path: Path) -> None:
    file = tmp_path / "ip_local_port_range"
    file.write_text("40000\t60999\n")
    assert ports.ephemeral_range(file) == (40000, 60999)
    file.write_text("garbage\n")
    assert ports.ephemeral_range(file) == ports.DEFAULT_EPHEMERAL
    assert ports.ephemeral_range(tmp_path / "absent") == ports.DEFAULT_EPHEMERAL


def test_a_process_takes_its_block_from_the_xdist_variables(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw3")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "4")
    picker = ports._ProcessPorts().picker()
    expected = ports.port_block(os.getpid(), "gw3", 4, ports.ephemeral_range()[0])
    assert picker is not None and picker.block == expected
