"""Loopback ports the host's NAT table sends elsewhere, held for the test session.

A container engine publishes a container's port with a DNAT rule in the host's ``nat``
table (podman's CNI portmap: ``-d 127.0.0.1/32 -p tcp --dport P -j DNAT --to
CONTAINER:6443`` for KinD's API server). The rule matches every connection to
127.0.0.1:P, not only the container's clients. When the engine fails to remove it with
the container, P stays redirected to an address nobody answers on: a test server that
the kernel later gives P (``bind`` to port 0 picks any free port of the ephemeral range)
listens, but every connection to it is sent away and its connect times out. That is how
a dashboard test's connect to its own server timed out here (port 44483, left by a KinD
run hours earlier).

So each pytest process binds 127.0.0.1:P for every such P before any test runs and
keeps the sockets open: the kernel then never hands P out. The sockets only hold the
port (``SO_REUSEADDR``, never listening), so every pytest-xdist worker can hold it too.
Reading the table needs root and ``iptables``; without either there is nothing to hold.
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess

_DNAT = re.compile(r"-j (DNAT|REDIRECT)\b")
_DEST = re.compile(r"-d (\S+)")
_PORTS = re.compile(r"--dports? (\S+)")


def redirected_loopback_ports(rules: str) -> list[int]:
    """The TCP ports of 127.0.0.1 that ``iptables -t nat -S`` output ``rules`` redirects."""
    ports: set[int] = set()
    for line in rules.splitlines():
        if not _DNAT.search(line) or "-p tcp" not in line:
            continue
        dest = _DEST.search(line)
        if dest is not None and dest.group(1) not in ("127.0.0.1", "127.0.0.1/32"):
            continue
        found = _PORTS.search(line)
        if found is None:
            continue
        for part in found.group(1).split(","):
            low, _, high = part.partition(":")
            ports.update(range(int(low), int(high or low) + 1))
    return sorted(ports)


def nat_rules() -> str:
    """``iptables -t nat -S`` (empty when it cannot be read: not root, no iptables)."""
    iptables = shutil.which("iptables") or shutil.which("iptables", path="/usr/sbin:/sbin")
    if iptables is None:
        return ""
    try:
        done = subprocess.run(
            [iptables, "-w", "5", "-t", "nat", "-S"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return done.stdout if done.returncode == 0 else ""


def hold(ports: list[int]) -> list[socket.socket]:
    """A socket bound to 127.0.0.1:port for each of ``ports`` that can be bound now."""
    held: list[socket.socket] = []
    for port in ports:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:  # in use by a listener: its clients are redirected, not ours
            sock.close()
            continue
        held.append(sock)
    return held
