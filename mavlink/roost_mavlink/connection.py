"""How an ``AutopilotSpec.connection`` URL maps to a pymavlink device.

Connection URLs (``AutopilotSpec.connection``) as the agent reads them:

- ``udp://HOST:PORT``: the agent LISTENS on HOST:PORT; the autopilot sends there. The
  agent locks onto the address the autopilot proves to send from and replies only there
  (pymavlink ``udpin:``; see ``roost_agent.trust``). ``udp://HOST:PORT@PEER[:PEERPORT]``
  (mavros' spelling of a remote end) fixes that address instead. An empty HOST listens
  on every interface.
- ``udpout://HOST:PORT``: the agent SENDS to HOST:PORT (pymavlink ``udpout:``).
- ``udpin://HOST:PORT`` is an explicit spelling of ``udp://``.
- ``tcp://HOST:PORT``: the agent connects (ArduPilot SITL); ``tcpin://`` listens.
- ``serial:///dev/ttyX:BAUD``: a serial device under ``/dev/``, baud optional (default
  57600).

Every port is 1-65535, ``udpout``/``tcp`` need a host, a baud is a positive integer;
anything else is refused here with a one-line reason, so the agent refuses it at start
instead of failing in its link thread.
"""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_SERIAL_BAUD = 57600


@dataclass(frozen=True)
class PymavlinkDevice:
    """Arguments for ``mavutil.mavlink_connection(device, baud=baud)``."""

    device: str
    baud: int = DEFAULT_SERIAL_BAUD
    peer: tuple[str, int | None] | None = None  # udp listeners: the only sender heard


def _port(text: str, connection: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise ValueError(f"connection {connection!r}: port {text or '(none)'} is not 1-65535")
    return int(text)


def _host_port(text: str, connection: str, *, need_host: bool) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        raise ValueError(f"connection {connection!r} lacks a port")
    if need_host and not host:
        raise ValueError(f"connection {connection!r} lacks a host")
    if any(c in host for c in "/@?#[] "):
        raise ValueError(f"connection {connection!r}: {host!r} is not a host name or address")
    return host, _port(port, connection)


def pymavlink_device(connection: str) -> PymavlinkDevice:
    """Translate an ``AutopilotSpec.connection`` URL into pymavlink's device string.

    Raises ValueError with a one-line reason for anything the agent could not open.
    """
    scheme, sep, rest = connection.partition("://")
    if not sep or not rest:
        raise ValueError(f"not a connection URL: {connection!r}")
    if scheme == "serial":
        if not rest.startswith("/dev/") or len(rest) <= len("/dev/"):
            raise ValueError(f"connection {connection!r}: a serial device is a path under /dev/")
        path, colon, baud = rest.rpartition(":")
        if not colon:
            return PymavlinkDevice(rest)
        if not baud.isdigit() or int(baud) <= 0:
            raise ValueError(f"connection {connection!r}: baud {baud!r} is not a positive number")
        return PymavlinkDevice(path, int(baud))
    prefix = {
        "udp": "udpin",
        "udpin": "udpin",
        "udpout": "udpout",
        "tcp": "tcp",
        "tcpin": "tcpin",
    }.get(scheme)
    if prefix is None:
        raise ValueError(f"unsupported connection scheme {scheme!r} in {connection!r}")
    local, at, remote = rest.partition("@")
    listens = prefix in ("udpin", "tcpin")
    host, port = _host_port(local, connection, need_host=not listens)
    peer: tuple[str, int | None] | None = None
    if at:
        if prefix != "udpin":
            raise ValueError(f"connection {connection!r}: only udp:// takes an @peer address")
        if ":" in remote:
            peer_host, peer_port = _host_port(remote, connection, need_host=True)
            peer = (peer_host, peer_port)
        elif remote and not any(c in remote for c in "/@?#[] "):
            peer = (remote, None)
        else:
            raise ValueError(f"connection {connection!r}: bad @peer address")
    return PymavlinkDevice(f"{prefix}:{host or '0.0.0.0'}:{port}", peer=peer)
