"""Follower <-> monitor messages: small JSON objects in UDP datagrams.

UDP because it works the same between processes on one machine (the sandbox: the monitor
on ``127.0.0.1``) and between pods (the monitor behind a Service with a UDP port; the
onboard pods reach it by the Service's DNS name), and because a lost message is only
late information here: followers repeat their reports until the monitor confirms them.

Messages (``type``):

- follower -> monitor: ``hello`` (every 0.5 s: alive, ``ready`` once at its start
  point), ``delay`` (``task``, ``delay``), ``leave`` (stopping early), ``done``
  (``records`` and the flown ``path`` for the table and the plot);
- monitor -> followers: ``start`` (``at``: the mission start, Unix time), ``members``
  (the live vehicles), ``pause`` (a vehicle's ``delay`` for a ``task``, forwarded to all:
  the paper's NotifyPause).
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import socket
from typing import Any

Message = dict[str, Any]
MAX_DATAGRAM = 65_000


def parse_address(text: str, default_port: int) -> tuple[str, int]:
    """``host:port`` (or ``host``) as a socket address."""
    host, _, port = text.rpartition(":") if ":" in text else (text, "", "")
    return (host or text, int(port) if port else default_port)


def bind_towards(peer: tuple[str, int]) -> tuple[str, int]:
    """Where a client talking to ``peer`` binds: the loopback for a local peer (nothing
    else hears it); any address of this network stack for a peer elsewhere (a Service's
    address in a cluster), from which the peer's answers come back."""
    try:
        local = ipaddress.ip_address(peer[0]).is_loopback
    except ValueError:  # a name: "localhost", or a Service's name
        local = peer[0] == "localhost"
    return ("127.0.0.1", 0) if local else ("0.0.0.0", 0)


class Channel:
    """One UDP socket sending and receiving JSON messages."""

    def __init__(self, bind: tuple[str, int] = ("127.0.0.1", 0)) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)
        self.sock.setblocking(False)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()[:2]
        return str(host), int(port)

    def send(self, message: Message, to: tuple[str, int]) -> None:
        data = json.dumps(message, separators=(",", ":")).encode()
        if len(data) > MAX_DATAGRAM:
            raise ValueError(f"message of {len(data)} bytes does not fit a datagram")
        with contextlib.suppress(OSError):  # the peer is not there (yet): repeated later
            self.sock.sendto(data, to)

    def receive(self) -> list[tuple[Message, tuple[str, int]]]:
        """Every message waiting now (malformed datagrams are dropped)."""
        out: list[tuple[Message, tuple[str, int]]] = []
        while True:
            try:
                data, sender = self.sock.recvfrom(MAX_DATAGRAM + 1)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out
            try:
                message = json.loads(data)
            except ValueError:
                continue
            if isinstance(message, dict) and isinstance(message.get("type"), str):
                out.append((message, (str(sender[0]), int(sender[1]))))

    def close(self) -> None:
        self.sock.close()
