"""The agents' telemetry stream as both ends read it: the local frame and its origin, and
where the stream is.

The agent (:mod:`roost_agent.telemetry`) sends metres north and east of an origin with
the latitude and longitude they came from; the dashboard puts every vehicle into its own
frame with the same projection, so a vehicle is drawn where its agent says it is, even
when agents measure from different origins.

Where: the agent writes its Vehicle's annotations itself (:func:`telemetry_annotations`):
the stream's URL, and the pod serving it, through whose API server pod proxy
(:func:`pod_proxy_path`) a dashboard anywhere reaches the agent with its own kubeconfig
— nothing on the vehicle is opened for it beyond the stream's port on the node's
address, which the API server dials, and the dashboard's user needs ``get`` on
``pods/proxy`` in the agent's namespace. A stream bound to the loopback is reachable
from nowhere else, so it is not announced.
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass

from roost_api.wellknown import ANNOTATION_TELEMETRY, ANNOTATION_TELEMETRY_POD

EARTH_RADIUS_M = 6_371_000.0
MAX_HZ = 10.0
"""The stream's highest rate: what a person can follow, and cheap for the agent."""


@dataclass(frozen=True)
class Origin:
    """Where north = east = 0 (degrees)."""

    lat: float
    lon: float

    @classmethod
    def parse(cls, text: str) -> Origin:
        """``LAT,LON`` in degrees."""
        lat_text, sep, lon_text = text.partition(",")
        try:
            lat, lon = float(lat_text), float(lon_text)
        except ValueError:
            lat = lon = math.nan
        if not sep or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ValueError(f"expected LAT,LON in degrees, not {text!r}")
        return cls(lat, lon)


def north_east_m(origin: Origin, lat: float, lon: float) -> tuple[float, float]:
    """Metres north and east of ``origin`` (equirectangular: exact enough over a field)."""
    k = math.pi / 180
    north = (lat - origin.lat) * k * EARTH_RADIUS_M
    east = (lon - origin.lon) * k * math.cos((lat + origin.lat) / 2 * k) * EARTH_RADIUS_M
    return north, east


def _loopback(address: str) -> bool:
    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


def telemetry_annotations(
    address: str, port: int, *, pod: str | None, namespace: str | None
) -> dict[str, str]:
    """The Vehicle annotations announcing a stream served on ``address:port`` by ``pod``
    in ``namespace``: the URL (unless bound to every address, which names none) and the
    pod (when known). Empty when bound to the loopback: nothing off the vehicle reaches it.
    """
    if _loopback(address):
        return {}
    found = {}
    if address not in ("", "0.0.0.0", "::"):
        host = f"[{address}]" if ":" in address else address
        found[ANNOTATION_TELEMETRY] = f"ws://{host}:{port}/"
    if pod and namespace:
        found[ANNOTATION_TELEMETRY_POD] = f"{namespace}/{pod}:{port}"
    return found


_POD_REF = re.compile(r"^([a-z0-9][-a-z0-9]{0,62})/([a-z0-9][-a-z0-9.]{0,252}):([0-9]{1,5})$")


def pod_proxy_path(reference: str) -> str | None:
    """The API server path proxying to the pod in ``reference`` (``NAMESPACE/POD:PORT``, as
    :data:`~roost_api.wellknown.ANNOTATION_TELEMETRY_POD` holds it); None when malformed."""
    found = _POD_REF.match(reference.strip())
    if found is None or not 0 < int(found.group(3)) < 65536:
        return None
    namespace, pod, port = found.groups()
    return f"/api/v1/namespaces/{namespace}/pods/{pod}:{port}/proxy/"
