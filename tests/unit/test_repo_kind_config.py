"""kind-config.yaml against a JSON schema of KinD's v1alpha4 configuration
(tests/e2e/kind/kind-config.schema.json, written for Roost from KinD's documented
fields, strict like KinD's decoder), and the fleet it declares against the CRDs.

The real ``kind`` binary of the pinned version, and ``shellcheck`` on the KinD scripts,
are in ``tests/integration/test_kind_config_pinned_kind.py``.
"""

from __future__ import annotations

import json
from typing import Any

import jsonschema
import pytest
import yaml

from roost_localcluster.binaries import REPO_ROOT
from tests.support.kind import KIND_DIR, kind_config

SCHEMA = json.loads((KIND_DIR / "kind-config.schema.json").read_text())
VEHICLE_LABEL = "e2e.roost.dev/vehicle"


def _workers() -> list[dict[str, Any]]:
    return [node for node in kind_config()["nodes"] if node.get("role") == "worker"]


# -- the schema ------------------------------------------------------------------------


def test_kind_config_matches_the_v1alpha4_schema() -> None:
    jsonschema.Draft7Validator.check_schema(SCHEMA)
    jsonschema.validate(kind_config(), SCHEMA)


@pytest.mark.parametrize(
    ("change", "why"),
    [
        (lambda c: c["nodes"][1].update(extraMount=[]), "unknown field"),
        (lambda c: c.update(nodes=c["nodes"][1:]), "no control plane"),
        (lambda c: c["nodes"][1].update(role="vehicle"), "unknown role"),
        (lambda c: c.update(name="Roost_E2E"), "bad cluster name"),
        (lambda c: c["nodes"][1]["extraMounts"][0].update(propagation="Shared"), "bad enum"),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_schema_rejects_what_kind_rejects(change: Any, why: str) -> None:
    config = kind_config()
    change(config)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(config, SCHEMA)


def test_three_vehicle_workers_with_a_fake_serial_port_and_their_config() -> None:
    workers = _workers()
    assert len(workers) == 3
    roles = [node.get("role", "control-plane") for node in kind_config()["nodes"]]
    assert roles.count("control-plane") == 1
    for worker in workers:
        vehicle = worker["labels"][VEHICLE_LABEL]
        mounts = {m["containerPath"]: m for m in worker["extraMounts"]}
        assert mounts["/dev/ttyUSB0"]["hostPath"].startswith(".kind/")
        config_file = REPO_ROOT / mounts["/etc/starling/vehicle.config"]["hostPath"]
        assert mounts["/etc/starling/vehicle.config"]["readOnly"] is True
        assert f"VEHICLE_NAME={vehicle}" in config_file.read_text().splitlines()


def test_kind_values_mount_the_fake_serial_port_kind_config_provides() -> None:
    values = yaml.safe_load((REPO_ROOT / "charts" / "roost" / "values-kind.yaml").read_text())
    assert values["agent"]["devices"]["paths"] == ["/dev/ttyUSB0"]


# -- the real kind binary --------------------------------------------------------------


# -- the fleet run.sh applies and the scripts ------------------------------------------


def _fleet() -> list[dict[str, Any]]:
    return [doc for doc in yaml.safe_load_all((KIND_DIR / "fleet.yaml").read_text()) if doc]


def test_fleet_declares_the_identity_of_each_workers_host_file() -> None:
    vehicles = [doc for doc in _fleet() if doc["kind"] == "Vehicle"]
    cluster = kind_config()["name"]
    # KinD names workers <cluster>-worker, <cluster>-worker2, ... in config order.
    node_names = [f"{cluster}-worker{'' if i == 1 else i}" for i in range(1, 4)]
    assert [v["spec"]["nodeName"] for v in vehicles] == node_names
    for vehicle, worker in zip(vehicles, _workers(), strict=True):
        host_file = REPO_ROOT / next(
            m["hostPath"]
            for m in worker["extraMounts"]
            if m["containerPath"] == "/etc/starling/vehicle.config"
        )
        entries = dict(line.split("=", 1) for line in host_file.read_text().splitlines())
        assert vehicle["metadata"]["name"] == entries["VEHICLE_NAME"]
        assert vehicle["spec"]["sysid"] == int(entries["VEHICLE_MAVLINK_SYSID"])


def test_fleet_is_valid_against_the_crds() -> None:
    schemas = {}
    for path in (REPO_ROOT / "crds").glob("*.yaml"):
        crd = yaml.safe_load(path.read_text())
        schemas[crd["spec"]["names"]["kind"]] = crd["spec"]["versions"][0]["schema"][
            "openAPIV3Schema"
        ]
    for doc in _fleet():
        jsonschema.Draft4Validator(schemas[doc["kind"]]).validate(doc)
