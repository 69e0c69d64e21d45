"""The shapes admission enforces, checked as pure rules, and the places they protect.

The API server runs the CEL rules (tests/integration/test_control_plane.py sends every
manifest of examples/invalid to a real one); here the same regular expressions run in
Python, and the bounds are checked against what the operator really derives from a name
of maximal length: label values, object and container names, Event names, the
annotations Roost writes.
"""

from __future__ import annotations

import json
import re
from typing import Any

import pytest

from roost_api import shapes
from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.meta import Stack
from roost_api.sitl import DEFAULT_SLOTS_PER_VEHICLE, MAX_SITL_INSTANCES, sitl_endpoint
from roost_api.vehicle import MAX_SIM_INSTANCE, VehicleSpec
from roost_kube.events import event_manifest
from roost_mavlink import pymavlink_device
from roost_operator.missions.workloads import offboard_job_name, onboard_job_name
from roost_operator.vehicles.config import config_map_name, vehicle_config, vehicle_config_map
from roost_operator.vehicles.manifests import autopilots_of, component_pod, component_workloads
from roost_operator.vehicles.placement import desired_node_labels, vehicle_taint

LABEL_VALUE = re.compile(shapes.LABEL_VALUE_PATTERN)
DNS_LABEL = re.compile(rf"^{shapes.DNS_LABEL}$")
DNS_SUBDOMAIN = re.compile(rf"^{shapes.DNS_SUBDOMAIN}$")


def full(pattern: str, text: str) -> bool:
    return re.search(pattern, text) is not None


def valid_connection(url: str) -> bool:
    """The three CEL connection rules, evaluated with Python's re."""
    if not full(shapes.CONNECTION_SCHEME_PATTERN, url):
        return False
    if full(shapes.NETWORK_SCHEME_PATTERN, url) and not full(shapes.NETWORK_CONNECTION, url):
        return False
    return not url.startswith("serial://") or full(shapes.SERIAL_CONNECTION, url)


@pytest.mark.parametrize(
    "url",
    [
        "udp://127.0.0.1:14540",
        "udpin://0.0.0.0:1",
        "udpout://10.0.0.2:65535",
        "tcp://localhost:5760",
        "tcpin://drone-1.fleet.local:5760",
        "serial:///dev/ttyUSB0:921600",
        "serial:///dev/serial/by-id/usb-FTDI_FT232R-if00-port0:57600",
        "serial:///dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0:115200",
        "udp://127.0.0.1:14540@127.0.0.1:14580",
        "udpin://0.0.0.0:14540@192.168.8.2",
    ],
)
def test_connection_urls_the_agent_can_open_are_accepted(url: str) -> None:
    assert valid_connection(url)
    device = pymavlink_device(url)  # the agent's own parser agrees on host, port and baud
    if url.startswith("serial://"):
        assert device.device.startswith("/dev/") and device.baud == int(url.rsplit(":", 1)[1])
    else:
        assert device.device.endswith(":" + url.split("@", maxsplit=1)[0].rsplit(":", 1)[1])


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8080",
        "udp://127.0.0.1:0",
        "udp://127.0.0.1:65536",
        "udp://127.0.0.1:70000",
        "udp://127.0.0.1:014540",
        "udp://:14540",
        "udp://127.0.0.1",
        "udp://127.0.0.1:",
        "udpout://256.1.1.1:14550",
        "udpout://1.2.3:14550",
        "udp://[::1]:14540",
        "tcp://bad_host:5760",
        "tcp://host name:5760",
        "serial:///tmp/ttyUSB0:57600",
        "serial:///dev/ttyUSB0",
        "serial:///dev/ttyUSB0:fast",
        "serial:///dev/ttyUSB0:0",
        "serial:///dev/../etc/shadow:57600",
        "serial:///dev/:57600",
        "udp://127.0.0.1:14540\nROOST_VEHICLE=x",
        "udpout://127.0.0.1:14540@127.0.0.1:14580",
        "tcp://127.0.0.1:5760@127.0.0.1",
        "udp://127.0.0.1:14540@",
        "udp://127.0.0.1:14540@127.0.0.1:0",
    ],
)
def test_connection_urls_that_cannot_work_are_refused(url: str) -> None:
    assert not valid_connection(url)


@pytest.mark.parametrize(
    ("url", "ok"),
    [
        ("udp://127.0.0.1:14540", True),
        ("udp://:14540@127.0.0.1:14557", True),
        ("udp://127.0.0.1:14641@", True),
        ("udp-b://@:14550", True),
        ("tcp://192.168.1.5:5760", True),
        ("tcp-l://:5760", True),
        ("serial:///dev/ttyACM0:57600", True),
        ("serial-hwfc:///dev/ttyS1:921600?ids=1,240", True),
        ("serial:///dev/px4fmu:115200", True),
        ("udp://127.0.0.1:14540 --extra", False),
        ("udp://:99999@127.0.0.1:14557", False),
        ("http://127.0.0.1", False),
        ("serial:///etc/passwd", False),
    ],
)
def test_fcu_urls_follow_mavros_grammar(url: str, ok: bool) -> None:
    assert any(full(p, url) for p in shapes.FCU_URL_PATTERNS) is ok


@pytest.mark.parametrize(
    ("value", "ok"),
    [
        ("plain value", True),
        ("tab\tseparated", True),
        ("ünïcödé and emoji 🛩", True),
        ("two\nlines", False),
        ("carriage\rreturn", False),
        ("nul\x00byte", False),
        ("escape\x1b[31m", False),
        ("next line\x85", False),
        ("line\u2028separator", False),
        ("paragraph\u2029separator", False),
        ("delete\x7f", False),
    ],
)
def test_config_values_are_one_line(value: str, ok: bool) -> None:
    assert (re.search(shapes.LINE_BREAK_PYTHON, value) is None) is ok
    # Every value Python's own line splitting would break is refused.
    if ok:
        assert len(value.splitlines()) == 1


def test_the_line_break_classes_for_re2_and_python_list_the_same_code_points() -> None:
    re2 = [int(h, 16) for h in re.findall(r"\\x\{([0-9a-f]+)\}", shapes.LINE_BREAK_RE2)]
    python = [int(h, 16) for h in re.findall(r"\\U([0-9a-f]{8})", shapes.LINE_BREAK_PYTHON)]
    assert re2 == python == [c for pair in shapes.LINE_BREAKING for c in pair]
    breaking = {chr(c) for lo, hi in shapes.LINE_BREAKING for c in range(lo, hi + 1)}
    splitting = {chr(c) for c in range(0x3000) if len(f"a{chr(c)}b".splitlines()) > 1}
    assert splitting <= breaking


@pytest.mark.parametrize(
    ("key", "ok"),
    [
        ("fleet", True),
        ("roost.dev/vehicle", True),
        ("app.kubernetes.io/name", True),
        ("a" * 63, True),
        ("a" * 64, False),
        ("fleet name", False),
        ("-fleet", False),
        ("Roost.dev/x", False),
        ("/fleet", False),
        (".".join(["p" * 60] * 5) + "/fleet", False),
    ],
)
def test_label_keys(key: str, ok: bool) -> None:
    assert (
        full(shapes.LABEL_KEY_PATTERN, key) and full(shapes.LABEL_KEY_PREFIX_PATTERN, key)
    ) is ok


@pytest.mark.parametrize(
    ("value", "ok"),
    [("", True), ("sandbox", True), ("a.b_c-d", True), ("-x", False), ("a b", False)],
)
def test_label_values(value: str, ok: bool) -> None:
    assert bool(LABEL_VALUE.fullmatch(value)) is ok


# ---- the bounds fit where Roost writes ------------------------------------------------


def longest_simulated_vehicle() -> tuple[str, VehicleSpec, RedundantAutopilotSpec]:
    name = "v" * shapes.VEHICLE_NAME_MAX
    spec = VehicleSpec.model_validate(
        {
            "nodeName": "n" * shapes.NODE_NAME_MAX,
            "sysid": 1,
            "simulation": {"stack": "ardupilot", "instance": MAX_SIM_INSTANCE},
            "components": {"vicon": {"enabled": True}, "hardware": {"enabled": True}},
        }
    )
    autopilots = RedundantAutopilotSpec.model_validate(
        {
            "vehicleName": name,
            "primary": "a" * shapes.AUTOPILOT_NAME_MAX,
            "autopilots": [
                {
                    "name": letter * shapes.AUTOPILOT_NAME_MAX,
                    "stack": "ardupilot",
                    "connection": f"tcp://127.0.0.1:{5760 + i}",
                    "sysid": i + 1,
                    "bridgeChannel": i,
                }
                for i, letter in enumerate("ab")
            ],
        }
    )
    return name, spec, autopilots


def labels_of(obj: dict[str, Any]) -> dict[str, str]:
    return dict(obj["metadata"].get("labels") or {})


def test_the_longest_names_fit_every_object_label_and_container_roost_derives() -> None:
    name, spec, autopilots = longest_simulated_vehicle()
    derived = autopilots_of(spec, autopilots)
    values = vehicle_config(
        name=name, spec=spec, fcu_url=derived[0].fcu_url, firmware=Stack.ARDUPILOT,
        active_autopilot=derived[0].name,
    )  # fmt: skip
    config_map = vehicle_config_map(name, values, namespace="roost-system")
    pods = [
        component_pod(name, spec.node_name, w, values, namespace="roost-system", owners=[])
        for w in component_workloads(spec, derived, vehicle_name="v")
    ]
    assert any(p["metadata"]["name"].endswith("-sitl-" + "b" * 58) for p in pods)
    for obj in [config_map, *pods]:
        assert DNS_SUBDOMAIN.fullmatch(obj["metadata"]["name"])
        assert len(obj["metadata"]["name"]) <= 253
        assert all(len(v) <= 63 and LABEL_VALUE.fullmatch(v) for v in labels_of(obj).values())
        for container in obj.get("spec", {}).get("containers", []):
            assert len(container["name"]) <= 63 and DNS_LABEL.fullmatch(container["name"])
    assert config_map_name(name) == config_map["metadata"]["name"]
    node_labels = desired_node_labels(name, spec)
    assert all(len(v) <= 63 and LABEL_VALUE.fullmatch(v) for v in node_labels.values())
    assert LABEL_VALUE.fullmatch(vehicle_taint(name)["value"])
    assert len(spec.node_name) <= 63 and LABEL_VALUE.fullmatch(spec.node_name)  # roost.dev/node


def test_the_highest_sim_instance_still_has_sitl_ports_for_every_slot() -> None:
    assert (MAX_SIM_INSTANCE + 1) * DEFAULT_SLOTS_PER_VEHICLE == MAX_SITL_INSTANCES
    for slot in range(DEFAULT_SLOTS_PER_VEHICLE):
        sitl_endpoint(MAX_SIM_INSTANCE, slot, Stack.PX4)
    with pytest.raises(ValueError, match="exceeds"):
        sitl_endpoint(MAX_SIM_INSTANCE + 1, 0, Stack.PX4)


def test_event_and_job_names_of_the_longest_mission_and_vehicle_are_valid() -> None:
    mission = "m" * shapes.MISSION_NAME_MAX
    vehicle = "v" * shapes.VEHICLE_NAME_MAX
    for job in (onboard_job_name(mission, vehicle), offboard_job_name(mission)):
        assert len(job) <= 63 and DNS_SUBDOMAIN.fullmatch(job)
    for kind, name in (("Mission", mission), ("Vehicle", vehicle)):
        regarding = {
            "apiVersion": "roost.dev/v1alpha1",
            "kind": kind,
            "metadata": {"name": name, "namespace": "default", "uid": "u"},
        }
        event = event_manifest(
            regarding,
            reason="Why",
            message="m",
            at="2026-01-01T00:00:00Z",
            component="roost-operator",
        )
        assert len(event["metadata"]["name"]) <= 253
        assert DNS_SUBDOMAIN.fullmatch(event["metadata"]["name"])


def _kopf_annotation(body: dict[str, Any]) -> str:
    """What kopf's AnnotationsDiffBaseStorage writes (its own build() and encoding)."""
    import kopf  # noqa: PLC0415 - the operator's dependency, needed only here

    storage = kopf.AnnotationsDiffBaseStorage(prefix="roost.dev", key="last-handled-configuration")
    essence = storage.build(body=kopf.Body(body))
    return json.dumps(essence, separators=(",", ":")) + "\n"


def _kubectl_annotation(body: dict[str, Any]) -> str:
    """What ``kubectl apply`` writes: Go's JSON, which escapes <, > and & as \\u00XX."""
    text = json.dumps(body, separators=(",", ":"), ensure_ascii=False)
    for char in "<>&":
        text = text.replace(char, f"\\u{ord(char):04x}")
    return text + "\n"


def test_the_largest_config_fits_the_annotations_roost_and_kubectl_write() -> None:
    # Worst case per character: a non-BMP character (12 bytes in kopf's ASCII JSON) and
    # '<' (6 bytes in kubectl's) cannot both be one character, so fill half with each.
    per_value = shapes.CONFIG_TOTAL_MAX // shapes.CONFIG_MAX_ENTRIES - 3  # "Kxx" keys
    config = {
        f"K{i:02d}": ("🛩" if i % 2 else "<") * per_value for i in range(shapes.CONFIG_MAX_ENTRIES)
    }
    assert sum(len(k) + len(v) for k, v in config.items()) <= shapes.CONFIG_TOTAL_MAX
    body: dict[str, Any] = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": "v" * 63, "labels": {"fleet": "sandbox"}},
        "spec": {
            "nodeName": "n" * 63,
            "sysid": 1,
            "components": {
                c: {"enabled": True, "image": "i" * 512} for c in ("mavros", "vicon", "hardware")
            },
            "simulation": {"stack": "px4", "instance": 9, "image": "s" * 512},
            "config": config,
        },
    }
    VehicleSpec.model_validate(body["spec"])
    kopf_bytes = len(_kopf_annotation(body).encode())
    kubectl_bytes = len(_kubectl_annotation(body).encode())
    bound = shapes.CONFIG_TOTAL_MAX * (shapes.KOPF_BYTES_PER_CHAR + shapes.KUBECTL_BYTES_PER_CHAR)
    bound += shapes.CONFIG_MAX_ENTRIES * shapes.JSON_BYTES_PER_ENTRY * 2
    config_bytes = len(json.dumps(config, separators=(",", ":")).encode()) + len(
        json.dumps(config, separators=(",", ":"), ensure_ascii=False).encode()
    )
    assert config_bytes <= bound
    # Everything Roost and kubectl keep, for the largest spec, with room to spare.
    assert kopf_bytes + kubectl_bytes < shapes.ANNOTATIONS_TOTAL_MAX - 100 * 1024
