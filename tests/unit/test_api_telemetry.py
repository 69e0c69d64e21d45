"""Where an agent's telemetry stream is: what the agent announces on its Vehicle, and
which URL the dashboard follows for it (directly, or through the API server's pod proxy).

All pure: the announcement and the endpoint resolution are functions of plain values (the
real-node suite follows a vehicle through a real API server's pod proxy).
"""

from __future__ import annotations

import ssl
from typing import Any

import pytest

from roost_agent.publisher import announcement
from roost_api.telemetry import pod_proxy_path, telemetry_annotations
from roost_api.wellknown import ANNOTATION_TELEMETRY, ANNOTATION_TELEMETRY_POD
from roost_cli.dashboard.model import FleetModel
from roost_cli.dashboard.sources import ApiProxy, Endpoints

POD = {"pod": "roost-agent-x7k2p", "namespace": "roost-system"}


@pytest.mark.parametrize(
    ("address", "pod", "expected"),
    [
        # bound to               pod known → annotations
        ("127.0.0.1", True, {}),  # on the vehicle only: nothing to announce
        ("::1", True, {}),
        ("localhost", True, {}),
        (
            "10.0.0.5",
            True,
            {
                ANNOTATION_TELEMETRY: "ws://10.0.0.5:9467/",
                ANNOTATION_TELEMETRY_POD: "roost-system/roost-agent-x7k2p:9467",
            },
        ),
        ("10.0.0.5", False, {ANNOTATION_TELEMETRY: "ws://10.0.0.5:9467/"}),
        ("fd00::5", False, {ANNOTATION_TELEMETRY: "ws://[fd00::5]:9467/"}),
        ("0.0.0.0", True, {ANNOTATION_TELEMETRY_POD: "roost-system/roost-agent-x7k2p:9467"}),
        ("0.0.0.0", False, {}),
    ],
)
def test_what_an_agent_announces_decision_table(
    address: str, *, pod: bool, expected: dict[str, str]
) -> None:
    given: dict[str, Any] = POD if pod else {"pod": None, "namespace": None}
    assert telemetry_annotations(address, 9467, **given) == expected


def test_the_announcement_is_written_only_where_the_vehicle_lacks_it() -> None:
    wanted = telemetry_annotations("10.0.0.5", 9467, **POD)
    assert announcement({}, wanted) == wanted
    assert announcement({**wanted, "other": "kept"}, wanted) == {}
    moved = {**wanted, ANNOTATION_TELEMETRY_POD: "roost-system/roost-agent-old:9467"}
    assert announcement(moved, wanted) == {
        ANNOTATION_TELEMETRY_POD: "roost-system/roost-agent-x7k2p:9467"
    }


@pytest.mark.parametrize(
    ("reference", "path"),
    [
        (
            "roost-system/roost-agent-x7k2p:9467",
            "/api/v1/namespaces/roost-system/pods/roost-agent-x7k2p:9467/proxy/",
        ),
        ("roost-system/roost-agent-x7k2p", None),  # no port
        ("roost-system/roost-agent-x7k2p:0", None),
        ("roost-system/roost-agent-x7k2p:70000", None),
        ("../secrets/x:1", None),  # never another API path
        ("roost-system/Agent:1", None),
    ],
)
def test_pod_proxy_paths(reference: str, path: str | None) -> None:
    assert pod_proxy_path(reference) == path


def _vehicle(name: str, annotations: dict[str, str]) -> dict[str, Any]:
    return {"metadata": {"name": name, "annotations": annotations}}


def test_the_dashboard_prefers_flags_then_the_sandbox_then_the_pod_proxy() -> None:
    model = FleetModel()
    announced = telemetry_annotations("10.0.0.5", 9467, **POD)
    model.replace(
        "Vehicle",
        [
            _vehicle("a", announced),
            _vehicle("b", {ANNOTATION_TELEMETRY: "ws://10.0.0.6:9467/"}),  # set by hand
            _vehicle("c", announced),
            _vehicle("d", announced),
        ],
    )
    proxy = ApiProxy("https://api.example:6443", ssl.create_default_context())
    endpoints = Endpoints({"d": "ws://flag/"}, lambda: {"c": "ws://sandbox/"}, proxy)
    assert endpoints.resolve(model) == {
        "a": "wss://api.example:6443/api/v1/namespaces/roost-system/pods/"
        "roost-agent-x7k2p:9467/proxy/",
        "b": "ws://10.0.0.6:9467/",
        "c": "ws://sandbox/",
        "d": "ws://flag/",
    }
    # Without a cluster the announced direct URL is all there is.
    assert Endpoints().resolve(model)["a"] == "ws://10.0.0.5:9467/"


def test_only_the_api_servers_own_urls_get_its_credentials() -> None:
    context = ssl.create_default_context()
    proxy = ApiProxy("https://api.example:6443/", context, lambda: {"Authorization": "Bearer t"})
    url = proxy.url("roost-system/roost-agent-x7k2p:9467")
    assert url is not None
    assert proxy.options(url) == {
        "ssl": context,
        "additional_headers": {"Authorization": "Bearer t"},
    }
    assert proxy.options("ws://10.0.0.5:9467/") == {}
    assert proxy.options("wss://api.example:6443.evil/x") == {}
