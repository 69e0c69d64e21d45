"""What the agent's hub costs per routed message, as a whole process, like a router.

The agent runs as its own process (``roost-agent --cluster off``, simulated bridge), the
image's build (its per-message path compiled by mypyc), with two autopilots configured
and the hub on a UDP port. Paced senders (their own processes) stream PX4's recorded
onboard mix (:data:`roost_sim.streams.PX4_STREAMS`, ~400 messages/s, every rate scaled
for faster streams) from the autopilots' system ids to the agent's autopilot ports; a
client greets the hub with a ground-station HEARTBEAT once a second and counts the
frames that reach it. CPU is the agent process's user + system time from the first
paced message to a second after the last, per 10,000 frames that reached the clients.

- ``hub.agent_cpu_ms_per_10k_routed_1to1_400`` / ``_2000``: one autopilot sends, one
  client (fc2 configured but silent, so one stream is read, as a router reads one).
- ``hub.loss_pct_1to1_5000``: frames the active autopilot sent that did not reach the
  client at 5,000 messages/s. Measured once the autopilot's address holds the link's
  source lock: a new source's first frames are dropped until it proves itself with two
  autopilot HEARTBEATs (``roost_agent.trust``), a second or two of its stream.
- ``hub.agent_cpu_ms_per_10k_routed_2x2_400``: both autopilots send at 400 messages/s
  (the agent reads both), the active one's stream goes to two clients.
- ``hub.router_cpu_ms_per_10k_routed_1to1_400`` / ``_2000`` (only with
  ``ROOST_BENCH_ROUTER``: the path of a ``mavlink-routerd`` binary): the C router measured
  the same way, right before the agent, on the same machine: the side-by-side that says
  what the agent's figures are worth there (a router's cost per message follows the
  machine's system-call and wake-up costs, which differ by several times between hosts).
- ``hub.syscalls_per_routed_msg``: ``strace -c -f`` on the agent for a window at 2,000
  messages/s, every system call of every thread, per frame routed in it (strace slows
  the agent, so fewer messages share a wake-up than without it: an upper bound).

Knobs (environment): ``ROOST_BENCH_HUBCOST_S`` (seconds per measurement, default 20),
``ROOST_BENCH_ROUTER`` (a ``mavlink-routerd`` to measure beside the agent; none: the
agent alone).
"""

from __future__ import annotations

import multiprocessing
import os
import random
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import psutil

from bench.agent import _load
from bench.core import Figure
from roost_api.autopilot import HubSpec
from roost_mavlink.codec import CRC_BYTES, frame_crc
from roost_sim.streams import PX4_STREAMS
from roost_sim.vehicle import free_udp_port
from tests.support.agent import AgentProcess
from tests.support.compiled import compiled_tree
from tests.support.compiled import environment as compiled_environment
from tests.support.flight import px4_pair_on_udp

SECONDS = float(os.environ.get("ROOST_BENCH_HUBCOST_S", "20"))
COMMAND = "python -m bench hubcost"
WARM_S = 4.0  # two proof heartbeats (1 Hz) and the agent's stream checks
SETTLE_S = 1.0
BASE_RATE = sum(s.hz for s in PX4_STREAMS.values())
PACING_S = 0.0001
"""A frame due within this long is sent at once, else the sender sleeps until it is due:
a paced sender's resolution, as fine as a Python sender's sleep allows. Coarser pacing
sends more frames of different streams together, which a reader then takes in one
wake-up: cheaper for the agent and a router alike, and less like a stream whose frames
each leave when they are due."""


BOOT_MS = 100_000
"""The senders' first ``time_boot_ms``: it advances with the stream (a PX4 in flight),
and from here until 4.6 h its third byte is never zero and its fourth always is, so a
frame's truncated MAVLink 2 payload keeps its length when the time is written into it."""
ESTIMATOR_HEALTHY = 0x3F  # attitude, velocities, positions: what a flying PX4 reports


@dataclass
class _Kind:
    """One message kind's frames, one per sequence number, and where their
    ``time_boot_ms`` sits (None: the message has none)."""

    by_seq: list[bytes]
    time_at: int | None
    crc_extra: int


def _encode(mavlink: Any, mav: Any, cls: Any, boot_ms: int, seq: int) -> bytes:
    """One frame of message class ``cls``: fields zero but what a healthy flying PX4
    says (armed heartbeat, healthy estimator, ``time_boot_ms``)."""
    values: list[object] = []
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    for name, kind in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        length = lengths[name]
        if kind == "char":
            values.append(b"")
        elif length:
            values.append([0] * length)
        elif kind in ("float", "double"):
            values.append(0.0)
        else:
            values.append(0)
        if name == "time_boot_ms":
            values[-1] = boot_ms
        elif name == "flags" and cls.id == mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS:
            values[-1] = ESTIMATOR_HEALTHY
    msg = cls(*values)
    if cls.id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:  # PX4, armed, ACTIVE
        msg = mavlink.MAVLink_heartbeat_message(2, 12, 0xD9, 0, 4, 3)
    mav.seq = seq
    return bytes(msg.pack(mav, force_mavlink1=False))


def _frames(kinds: list[int], sysid: int) -> list[_Kind]:
    """Per message kind, its frame (:func:`_encode`) with each of the 256 sequence
    numbers (the number is under the CRC); ``time_boot_ms`` is written in as it is sent."""
    from pymavlink.dialects.v20 import all as mavlink  # noqa: PLC0415 - the sender only

    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
    out = []
    for msg_id in kinds:
        cls = mavlink.mavlink_map[msg_id]

        by_seq = [_encode(mavlink, mav, cls, BOOT_MS, seq) for seq in range(256)]
        # where the time is: the first byte that differs between two times
        other = _encode(mavlink, mav, cls, BOOT_MS + 0x101, 0)
        time_at = next(
            (i for i, (a, b) in enumerate(zip(by_seq[0], other, strict=True)) if a != b), None
        )
        out.append(_Kind(by_seq, time_at, cls.crc_extra))
    return out


def _stamped(kind: _Kind, seq: int, boot_ms: int) -> bytes:
    """``kind``'s frame numbered ``seq`` saying ``boot_ms`` (its CRC recomputed)."""
    frame = kind.by_seq[seq]
    at = kind.time_at
    if at is None:
        return frame
    out = bytearray(frame)
    out[at : at + 4] = boot_ms.to_bytes(4, "little")
    end = len(out) - CRC_BYTES
    crc = frame_crc(out[1:end], kind.crc_extra)
    out[end] = crc & 0xFF
    out[end + 1] = crc >> 8
    return bytes(out)


def _sender(conn: Connection, port: int, sysid: int) -> None:
    """Streams the PX4 mix to ``port`` on request: ("run", rate, seconds) -> sent.
    One socket for the process's life: the agent's source lock keeps holding it."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    kinds = sorted(PX4_STREAMS)
    frames = _frames(kinds, sysid)
    born = time.monotonic()
    while True:
        request = conn.recv()
        if request is None:
            return
        _, rate, seconds = request
        scale = rate / BASE_RATE
        # one second of the mix, (offset, frame) in time order, repeated; each stream at
        # a phase of its own, so few messages leave together and nearly every one is a
        # wake-up of its own for whoever reads them (the harder case for a router)
        phases = random.Random(sysid)
        second = sorted(
            (((phase + i) / (PX4_STREAMS[k].hz * scale)) % 1.0, n)
            for n, k in enumerate(kinds)
            for phase in [phases.random()]
            for i in range(max(1, round(PX4_STREAMS[k].hz * scale)))
        )
        seq = sent = 0
        start = time.monotonic()
        for whole in range(int(seconds)):
            for offset, n in second:
                due = start + whole + offset
                wait = due - time.monotonic()
                if wait > PACING_S:
                    time.sleep(wait)
                boot_ms = BOOT_MS + int((due - born) * 1000)
                sock.sendto(_stamped(frames[n], seq, boot_ms), ("127.0.0.1", port))
                seq = (seq + 1) % 256
                sent += 1
        conn.send(sent)


class _Counter(threading.Thread):
    """A hub client: greets the hub once a second, counts the MAVLink 2 frames arriving
    from the autopilot's component (1; the agent's own frames, component 191, are not)."""

    def __init__(self, hub: tuple[str, int] | None) -> None:
        super().__init__(daemon=True)
        from pymavlink.dialects.v20 import common as mavlink  # noqa: PLC0415

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.greeting = bytes(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav))
        self.hub = hub
        self.frames = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        greeted = 0.0
        while not self.stopping.is_set():
            if self.hub is not None and time.monotonic() - greeted > 1.0:
                self.sock.sendto(self.greeting, self.hub)
                greeted = time.monotonic()
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            i = 0
            while i + 12 <= len(data) and data[i] == 0xFD:
                self.frames += data[i + 6] == 1
                i += 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)

    def stop(self) -> None:
        self.stopping.set()
        self.join(2)
        self.sock.close()


@contextmanager
def _rig(clients: int) -> Iterator[tuple[AgentProcess, list[Connection], list[_Counter]]]:
    ports = [free_udp_port(), free_udp_port()]
    hub_port = free_udp_port()
    spec = px4_pair_on_udp("hubcost", ports, HubSpec(udp=f"127.0.0.1:{hub_port}", sysid=1))
    ctx = multiprocessing.get_context("spawn")
    pipes, senders = [], []
    for i, port in enumerate(ports):
        ours, theirs = ctx.Pipe()
        proc = ctx.Process(target=_sender, args=(theirs, port, i + 1), daemon=True)
        proc.start()
        pipes.append(ours)
        senders.append(proc)
    counters = [_Counter(("127.0.0.1", hub_port)) for _ in range(clients)]
    with tempfile.TemporaryDirectory(prefix="roost-bench-hubcost-") as tmp:
        agent = AgentProcess.standalone(Path(tmp), spec, status_interval_s=5.0, log_level="WARNING")
        try:
            for counter in counters:
                counter.start()
            yield agent, pipes, counters
        finally:
            agent.stop()
            for counter in counters:
                counter.stop()
            for pipe in pipes:
                pipe.send(None)
            for proc in senders:
                proc.join(5)
                if proc.is_alive():
                    proc.kill()


@contextmanager
def _router_rig(router: str) -> Iterator[tuple[int, list[Connection], list[_Counter]]]:
    """``mavlink-routerd`` (a build of it given by path, kept outside the repository)
    with one UDP endpoint in (server: the autopilot sends to it) and one out (to a
    counting client), fed by the same paced sender as the agent: its pid, the sender's
    pipe, the client."""
    in_port = free_udp_port()
    counter = _Counter(None)
    out_port = counter.sock.getsockname()[1]
    ctx = multiprocessing.get_context("spawn")
    ours, theirs = ctx.Pipe()
    sender = ctx.Process(target=_sender, args=(theirs, in_port, 1), daemon=True)
    with tempfile.TemporaryDirectory(prefix="roost-bench-router-") as tmp:
        conf = Path(tmp) / "router.conf"
        conf.write_text(
            "[General]\nTcpServerPort = 0\nReportStats = false\n"
            f"[UdpEndpoint in]\nMode = Server\nAddress = 127.0.0.1\nPort = {in_port}\n"
            f"[UdpEndpoint out]\nMode = Normal\nAddress = 127.0.0.1\nPort = {out_port}\n"
        )
        (Path(tmp) / "conf.d").mkdir()
        proc = subprocess.Popen(
            [router, "-c", str(conf), "-d", str(Path(tmp) / "conf.d")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            sender.start()
            counter.start()
            time.sleep(1.0)
            yield proc.pid, [ours], [counter]
        finally:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            counter.stop()
            ours.send(None)
            sender.join(5)
            if sender.is_alive():
                sender.kill()


def _cpu_s(pid: int) -> float:
    times = psutil.Process(pid).cpu_times()
    return float(times.user + times.system)


def _run(pipes: list[Connection], rate: float, seconds: float) -> list[int]:
    for pipe in pipes:
        pipe.send(("run", rate, seconds))
    return [int(pipe.recv()) for pipe in pipes]


def _measure(
    pid: int, pipes: list[Connection], counters: list[_Counter], rate: float
) -> tuple[float, float, int]:
    """(CPU ms per 10k frames routed, % of the active's frames lost, frames routed) of
    the process ``pid``."""
    before = sum(c.frames for c in counters)
    cpu0 = _cpu_s(pid)
    sent = _run(pipes, rate, SECONDS)
    time.sleep(SETTLE_S)
    cpu1 = _cpu_s(pid)
    routed = sum(c.frames for c in counters) - before
    per_client = routed / len(counters)
    lost_pct = max(0.0, (sent[0] - per_client) * 100 / sent[0])
    return (cpu1 - cpu0) * 1000 / max(routed, 1) * 10_000, lost_pct, routed


def _syscalls(agent: AgentProcess, pipes: list[Connection], counters: list[_Counter]) -> str:
    """strace -c -f on the agent for a 2,000 messages/s window: 'calls per frame; top'."""
    strace = shutil.which("strace")
    if strace is None:
        return ""
    before = sum(c.frames for c in counters)
    with tempfile.NamedTemporaryFile("r", suffix=".strace") as out:
        tracer = subprocess.Popen(
            [strace, "-c", "-f", "-o", out.name, "-p", str(agent.pid)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(1.0)
        _run(pipes[:1], 2000, 5)
        tracer.terminate()
        tracer.wait(10)
        report = Path(out.name).read_text()
    routed = sum(c.frames for c in counters) - before
    rows = re.findall(r"^\s*[\d.]+\s+[\d.]+\s+\d+\s+(\d+)\s+(?:\d+\s+)?(\w+)\s*$", report, re.M)
    total = sum(int(calls) for calls, name in rows if name != "total")
    top = sorted(((int(c), n) for c, n in rows if n != "total"), reverse=True)[:4]
    per = ", ".join(f"{n} {c / max(routed, 1):.2f}" for c, n in top)
    return f"{total / max(routed, 1):.2f}|{routed}|{per}"


def _router_figures() -> tuple[list[Figure], dict[int, str]]:
    """The router's own figures (``ROOST_BENCH_ROUTER`` set), and per rate what the
    agent's notes say of it; nothing when no router is given."""
    router = os.environ.get("ROOST_BENCH_ROUTER", "")
    if not router:
        return [], {}
    if not os.access(router, os.X_OK):
        raise SystemExit(f"ROOST_BENCH_ROUTER: {router} is not an executable")
    with _router_rig(router) as (pid, pipes, counters):
        _run(pipes, 400, WARM_S)
        measured = {rate: _measure(pid, pipes, counters, rate) for rate in (400, 2000)}
        load = _load()
    figures, notes = [], {}
    for rate, (cpu, lost, routed) in measured.items():
        notes[rate] = f"; mavlink-routerd in the same run, same sender and client: {cpu:.0f}"
        figures.append(
            Figure(
                f"hub.router_cpu_ms_per_10k_routed_1to1_{rate}",
                round(cpu, 1),
                "ms",
                "informational",
                f"ROOST_BENCH_ROUTER=/path/to/mavlink-routerd {COMMAND}",
                f"mavlink-routerd (a build kept outside the repository) as the agent is "
                f"measured right after it: process user+system CPU per 10,000 frames that "
                f"reached its one UDP client, {rate} msg/s of the same paced mix for "
                f"{SECONDS:.0f} s, {routed} routed, {lost:.2f} % lost; 1-min load {load}",
            )
        )
    return figures, notes


def run() -> list[Figure]:
    os.environ.update(compiled_environment(compiled_tree()))
    figures, router_notes = _router_figures()
    with _rig(clients=1) as (agent, pipes, counters):
        one = pipes[:1]
        _run(one, 400, WARM_S)  # the source lock, the agent's stream checks
        results = {rate: _measure(agent.pid, one, counters, rate) for rate in (400, 2000, 5000)}
        load = _load()
        traced = _syscalls(agent, pipes, counters)
    with _rig(clients=2) as (agent, pipes, counters):
        _run(pipes, 400, WARM_S)
        both = _measure(agent.pid, pipes, counters, 400)
        load2 = _load()
    where = (
        "roost-agent (the image's compiled build) process user+system CPU, one autopilot "
        "sending PX4's recorded onboard mix, one hub client, per 10,000 frames that reached it"
    )
    for rate in (400, 2000):
        cpu, lost, routed = results[rate]
        figures.append(
            Figure(
                f"hub.agent_cpu_ms_per_10k_routed_1to1_{rate}",
                round(cpu, 1),
                "ms",
                "<= 120",
                COMMAND,
                f"{where}: {rate} msg/s for {SECONDS:.0f} s, {routed} routed, {lost:.2f} % "
                f"lost; 1-min load {load} (2 cores shared){router_notes.get(rate, '')}",
            )
        )
    cpu, lost, routed = results[5000]
    figures.append(
        Figure(
            "hub.loss_pct_1to1_5000",
            round(lost, 3),
            "%",
            "== 0",
            COMMAND,
            f"5,000 msg/s for {SECONDS:.0f} s from an autopilot holding the link's source lock, "
            f"{routed} routed to one client ({cpu:.0f} ms CPU per 10k); a new source's first "
            "frames are dropped until two autopilot HEARTBEATs prove it (source lock); "
            f"1-min load {load}",
        )
    )
    cpu2, lost2, routed2 = both
    figures.append(
        Figure(
            "hub.agent_cpu_ms_per_10k_routed_2x2_400",
            round(cpu2, 1),
            "ms",
            "informational",
            COMMAND,
            f"two autopilots sending 400 msg/s each (both read), the active one's routed to two "
            f"clients: {routed2} frames reached them in {SECONDS:.0f} s ({lost2:.2f} % of the "
            f"active's lost per client); 1-min load {load2}",
        )
    )
    if traced:
        per, routed_traced, top = traced.split("|")
        figures.append(
            Figure(
                "hub.syscalls_per_routed_msg",
                float(per),
                "calls",
                "informational",
                COMMAND,
                f"strace -c -f on the agent (every thread) while one autopilot sent 2,000 msg/s "
                f"for 5 s to one client: {routed_traced} frames routed; per frame: {top}; "
                "strace slows the agent, so fewer frames share each wake-up than untraced",
            )
        )
    return figures
