"""Where simulated autopilots live on the network, and how connection URLs map to pymavlink.

Two autopilots must never share a system id or a port: pymavlink merges two autopilots
with one sysid behind one socket and a command then reaches both. Roost numbers SITL
instances globally, ``i = vehicle_instance * slots_per_vehicle + autopilot_index``, and
derives everything from ``i`` the way the stacks themselves do:

- PX4 SITL instance ``i``: ``MAV_SYS_ID = i + 1``; its onboard/API link sends to UDP
  ``14540 + i`` from local UDP ``14580 + i``. Valid for ``i < 40`` (from 40 on the two
  ranges overlap). Note: instance 10 sends to 14550, the port a ground station on the same
  host listens on; keep ``i < 10`` when QGroundControl runs beside the fleet.
- ArduPilot SITL instance ``i`` (``-I i``): serial0 is a TCP server on ``5760 + 10 i``
  (serial1/2 on +2/+3); its sysid stays 1 unless ``SYSID_THISMAV`` is set, so Roost sets
  it to ``i + 1`` like PX4. For a UDP link Roost points ``--serial1 udpclient:`` at the
  same ``14540 + i`` port, so one agent config shape serves both stacks.

Connection URLs (``AutopilotSpec.connection``) as the agent reads them:

- ``udp://HOST:PORT``: the agent LISTENS on HOST:PORT; the autopilot sends there. The
  agent locks onto the address the autopilot proves to send from and replies only there
  (pymavlink ``udpin:``; see ``roost_agent.links``). ``udp://HOST:PORT@PEER[:PEERPORT]``
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

from roost_api.core import Stack

PX4_API_PORT_BASE = 14540
PX4_LOCAL_PORT_BASE = 14580
ARDUPILOT_TCP_PORT_BASE = 5760
ARDUPILOT_TCP_PORT_STEP = 10
MAX_SITL_INSTANCES = PX4_LOCAL_PORT_BASE - PX4_API_PORT_BASE
DEFAULT_SLOTS_PER_VEHICLE = 4
DEFAULT_SERIAL_BAUD = 57600


@dataclass(frozen=True)
class SitlEndpoint:
    """Identity and ports of one simulated autopilot."""

    stack: Stack
    instance: int
    sysid: int
    agent_port: int  # UDP port the autopilot sends to; the agent listens here
    autopilot_port: int  # UDP port the autopilot sends from (PX4) / TCP server (ArduPilot)

    @property
    def connection(self) -> str:
        """The ``AutopilotSpec.connection`` an agent on the same host uses."""
        return f"udp://127.0.0.1:{self.agent_port}"


def sitl_instance(
    vehicle_instance: int, autopilot_index: int, slots_per_vehicle: int = DEFAULT_SLOTS_PER_VEHICLE
) -> int:
    """Global SITL instance number of one autopilot of one vehicle."""
    if vehicle_instance < 0 or not 0 <= autopilot_index < slots_per_vehicle:
        raise ValueError(
            f"autopilot index {autopilot_index} of vehicle {vehicle_instance} does not fit "
            f"{slots_per_vehicle} slots per vehicle"
        )
    return vehicle_instance * slots_per_vehicle + autopilot_index


def sitl_endpoint(
    vehicle_instance: int,
    autopilot_index: int,
    stack: Stack,
    slots_per_vehicle: int = DEFAULT_SLOTS_PER_VEHICLE,
) -> SitlEndpoint:
    """Sysid and ports for autopilot ``autopilot_index`` of vehicle ``vehicle_instance``."""
    stack = Stack(stack)
    i = sitl_instance(vehicle_instance, autopilot_index, slots_per_vehicle)
    if i >= MAX_SITL_INSTANCES:
        raise ValueError(f"SITL instance {i} exceeds the {MAX_SITL_INSTANCES} the ports allow")
    local = (
        PX4_LOCAL_PORT_BASE + i
        if stack is Stack.PX4
        else ARDUPILOT_TCP_PORT_BASE + ARDUPILOT_TCP_PORT_STEP * i
    )
    return SitlEndpoint(
        stack=stack, instance=i, sysid=i + 1, agent_port=PX4_API_PORT_BASE + i, autopilot_port=local
    )


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
