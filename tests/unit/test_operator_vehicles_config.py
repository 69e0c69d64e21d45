"""A vehicle's config values, its ConfigMap, and how any pod on the vehicle gets them."""

from __future__ import annotations

from roost_api.meta import Stack
from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import LABEL_VEHICLE, VEHICLE_CONFIG_FILE, VEHICLE_CONFIG_MOUNTS
from roost_operator.vehicles.config import (
    VOLUME_NAME,
    config_hash,
    config_map_name,
    config_values_of,
    mount_vehicle_config,
    render_vehicle_config,
    vehicle_config,
    vehicle_config_map,
)


def spec(**overrides: object) -> VehicleSpec:
    return VehicleSpec.model_validate(
        {"nodeName": "node-a", "sysid": 12, "config": {"ZETA": "z", "ALPHA": "a"}, **overrides}
    )


def values(fcu_url: str = "udp://127.0.0.1:14540") -> dict[str, str]:
    return vehicle_config(
        name="drone1",
        spec=spec(),
        fcu_url=fcu_url,
        firmware=Stack.PX4,
        active_autopilot="fc1",
    )


def test_config_has_starlings_keys_first_then_roosts_then_the_specs_sorted() -> None:
    config = values()
    keys = list(config)
    assert keys[:4] == [
        "VEHICLE_NAME",
        "VEHICLE_MAVLINK_SYSID",
        "VEHICLE_FCU_URL",
        "VEHICLE_FIRMWARE",
    ]
    assert keys[-2:] == ["ALPHA", "ZETA"]
    assert config["VEHICLE_NAME"] == "drone1"
    assert config["VEHICLE_MAVLINK_SYSID"] == "12"
    assert config["VEHICLE_FCU_URL"] == "udp://127.0.0.1:14540"
    assert config["VEHICLE_FIRMWARE"] == "px4"
    assert config["ROOST_NODE_NAME"] == "node-a"
    assert config["ROOST_SIMULATED"] == "false"
    assert config["ROOST_ACTIVE_AUTOPILOT"] == "fc1"


def test_rendered_file_is_one_key_value_line_per_entry() -> None:
    text = render_vehicle_config({"A": "1", "B": "x=y"})
    assert text == "A=1\nB=x=y\n"


def test_config_map_carries_the_file_and_every_key() -> None:
    config = values()
    cm = vehicle_config_map("drone1", config, namespace="ns", owners=[{"uid": "u"}])
    assert cm["metadata"]["name"] == config_map_name("drone1") == "roost-vehicle-drone1"
    assert cm["metadata"]["namespace"] == "ns"
    assert cm["metadata"]["labels"][LABEL_VEHICLE] == "drone1"
    assert cm["metadata"]["ownerReferences"] == [{"uid": "u"}]
    assert cm["data"][VEHICLE_CONFIG_FILE] == render_vehicle_config(config)
    assert config_values_of(cm) == config


def test_failover_changes_the_full_hash_but_not_the_failover_free_one() -> None:
    before, after = values("udp://127.0.0.1:14540"), values("udp://127.0.0.1:14541")
    assert config_hash(before) != config_hash(after)
    assert config_hash(before, include_failover_keys=False) == config_hash(
        after, include_failover_keys=False
    )


def test_spec_config_change_changes_both_hashes() -> None:
    base = values()
    changed = {**base, "ALPHA": "other"}
    assert config_hash(base) != config_hash(changed)
    assert config_hash(base, include_failover_keys=False) != config_hash(
        changed, include_failover_keys=False
    )


POD = {
    "restartPolicy": "Never",
    "volumes": [{"name": "scratch", "emptyDir": {}}],
    "initContainers": [{"name": "init", "image": "busybox"}],
    "containers": [
        {
            "name": "main",
            "image": "controller",
            "env": [{"name": "OWN", "value": "1"}, {"name": "VEHICLE_NAME", "value": "spoof"}],
            "volumeMounts": [{"name": "scratch", "mountPath": "/tmp/x"}],
        }
    ],
}


def test_mount_puts_the_file_read_only_at_both_paths_in_every_container() -> None:
    config = values()
    pod = mount_vehicle_config(POD, "drone1", config)
    volume = next(v for v in pod["volumes"] if v["name"] == VOLUME_NAME)
    assert volume["configMap"]["name"] == "roost-vehicle-drone1"
    assert volume["configMap"]["items"] == [{"key": "vehicle.config", "path": "vehicle.config"}]
    for container in pod["initContainers"] + pod["containers"]:
        mounts = [m for m in container["volumeMounts"] if m["name"] == VOLUME_NAME]
        assert sorted(m["mountPath"] for m in mounts) == sorted(VEHICLE_CONFIG_MOUNTS)
        assert all(m["readOnly"] for m in mounts)
    assert sorted(VEHICLE_CONFIG_MOUNTS) == ["/etc/roost", "/etc/starling"]


def test_mount_exports_every_key_from_the_config_map_and_keeps_the_pods_own_parts() -> None:
    config = values()
    pod = mount_vehicle_config(POD, "drone1", config)
    main = pod["containers"][0]
    refs = {e["name"]: e["valueFrom"]["configMapKeyRef"] for e in main["env"] if "valueFrom" in e}
    assert set(refs) == set(config)
    assert all(r == {"name": "roost-vehicle-drone1", "key": k} for k, r in refs.items())
    assert {"name": "OWN", "value": "1"} in main["env"]
    assert {"name": "VEHICLE_NAME", "value": "spoof"} not in main["env"]
    assert {"name": "scratch", "mountPath": "/tmp/x"} in main["volumeMounts"]
    assert {"name": "scratch", "emptyDir": {}} in pod["volumes"]
    assert pod["restartPolicy"] == "Never"


def test_mount_is_idempotent_and_does_not_modify_its_input() -> None:
    config = values()
    snapshot = repr(POD)
    once = mount_vehicle_config(POD, "drone1", config)
    assert mount_vehicle_config(once, "drone1", config) == once
    assert repr(POD) == snapshot
