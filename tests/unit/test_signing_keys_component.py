"""The per-Vehicle key pod: when the operator runs it, what it mounts, where it runs;
and the key hand-over it performs (real files in a temporary directory)."""

from __future__ import annotations

import stat
import threading
from pathlib import Path
from typing import Any

import pytest

from roost_agent.keysync import parse_owner, run, sync_once
from roost_agent.signing import KeyWatcher, LinkSigning, read_keys
from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import SIGNING_HOST_DIR
from roost_kube.patches import Obj
from roost_mavlink.signing import Timestamps
from roost_operator.vehicles.config import vehicle_config
from roost_operator.vehicles.desired import (
    DEFAULT_FCU_URL,
    DEFAULT_IMAGES,
    SIGNING_KEYS,
    component_pod,
    component_workloads,
    pod_hash,
)

KEY_A = "aa" * 32
KEY_B = "bb" * 32


def spec(signing_keys: dict[str, Any] | None = None, **overrides: object) -> VehicleSpec:
    components = {} if signing_keys is None else {"signingKeys": signing_keys}
    return VehicleSpec.model_validate(
        {"nodeName": "node-a", "sysid": 12, "components": components, **overrides}
    )


def key_pod(vehicle: str, s: VehicleSpec, node: str = "node-a") -> Obj:
    (workload,) = [
        w for w in component_workloads(s, [], vehicle_name=vehicle) if w.component == SIGNING_KEYS
    ]
    values = vehicle_config(
        name=vehicle, spec=s, fcu_url=DEFAULT_FCU_URL, firmware=None, active_autopilot=None
    )
    return component_pod(vehicle, node, workload, values, namespace="roost", owners=[])


# -- when: decision table ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("signing_keys", "simulated", "runs"),
    [
        (None, False, False),  # default: no key pod (a vehicle without signing)
        ({"enabled": False}, False, False),
        ({"enabled": True}, False, True),
        ({"enabled": True}, True, True),  # simulated vehicles sign too
        ({"enabled": True, "image": "registry.example/roost-agent:1"}, False, True),
    ],
)
def test_the_key_pod_runs_exactly_when_the_vehicle_asks_for_it(
    signing_keys: dict[str, Any] | None, simulated: bool, runs: bool
) -> None:
    extra: dict[str, object] = {"simulation": {"stack": "px4"}} if simulated else {}
    components = [
        w.component for w in component_workloads(spec(signing_keys, **extra), [], vehicle_name="d1")
    ]
    assert (SIGNING_KEYS in components) is runs


@pytest.mark.parametrize(
    ("image", "agent_image", "expected"),
    [
        (None, None, DEFAULT_IMAGES[SIGNING_KEYS]),
        (None, "roost-agent:1.4.0", "roost-agent:1.4.0"),  # the chart's agent image
        ("registry.example/roost-agent:1", "roost-agent:1.4.0", "registry.example/roost-agent:1"),
    ],
)
def test_the_key_pod_uses_the_agent_image_unless_the_vehicle_names_one(
    image: str | None, agent_image: str | None, expected: str
) -> None:
    workloads = component_workloads(
        spec({"enabled": True, "image": image}), [], vehicle_name="d1", agent_image=agent_image
    )
    assert [w.image for w in workloads if w.component == SIGNING_KEYS] == [expected]


# -- what and where ----------------------------------------------------------------------


@pytest.mark.parametrize("vehicle", ["drone-1", "drone-2"])
def test_the_key_pod_mounts_only_its_own_vehicles_secret_on_its_own_node(vehicle: str) -> None:
    pod = key_pod(vehicle, spec({"enabled": True}), node=f"node-of-{vehicle}")
    pod_spec = pod["spec"]
    assert pod_spec["nodeName"] == f"node-of-{vehicle}"
    secrets = [v["secret"]["secretName"] for v in pod_spec["volumes"] if "secret" in v]
    assert secrets == [f"roost-signing-{vehicle}"]
    host = [v["hostPath"]["path"] for v in pod_spec["volumes"] if "hostPath" in v]
    assert host == [f"{SIGNING_HOST_DIR}/{vehicle}"]
    # no API credentials: it reads its Secret through the kubelet only
    assert pod_spec["automountServiceAccountToken"] is False
    container = pod_spec["containers"][0]
    assert container["securityContext"]["capabilities"] == {"drop": ["ALL"], "add": ["CHOWN"]}
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert "--owner=65532:65532" in container["args"]


def test_the_secret_name_cannot_be_chosen_by_the_spec() -> None:
    """Only the Vehicle's name picks the Secret: a Vehicle cannot have another Secret
    mounted on its node (the spec has no field that names one; an unknown one is
    dropped)."""
    pod = key_pod("d1", spec({"enabled": True, "secretName": "roost-operator-token"}))
    secrets = [v["secret"]["secretName"] for v in pod["spec"]["volumes"] if "secret" in v]
    assert secrets == ["roost-signing-d1"]


def test_a_node_change_replaces_the_key_pod() -> None:
    s = spec({"enabled": True})
    assert pod_hash(key_pod("d1", s, "node-a")) != pod_hash(key_pod("d1", s, "node-b"))


# -- the hand-over ----------------------------------------------------------------------


def secret_dir(tmp_path: Path, key: str, previous: str = "") -> Path:
    source = tmp_path / "secret"
    source.mkdir(exist_ok=True)
    (source / "key").write_text(key)
    (source / "previous").write_text(previous)
    return source


def test_sync_writes_the_key_mode_0600_in_a_0700_directory_the_agent_reads(
    tmp_path: Path,
) -> None:
    source = secret_dir(tmp_path, KEY_A)
    target = tmp_path / "host" / "d1"
    assert sync_once(source, target) == ["key"]  # an empty previous is not written
    assert stat.S_IMODE((target / "key").stat().st_mode) == 0o600
    assert stat.S_IMODE(target.stat().st_mode) == 0o700
    assert not (target / "previous").exists()
    assert read_keys(tmp_path / "host", "d1") == (bytes.fromhex(KEY_A), None)
    assert sync_once(source, target) == []  # nothing changed, nothing written


def test_a_rotation_reaches_the_agents_key_watcher(tmp_path: Path) -> None:
    source = secret_dir(tmp_path, KEY_A)
    host = tmp_path / "host"
    sync_once(source, host / "d1")
    current = LinkSigning(key=bytes.fromhex(KEY_A), require=True, clock=Timestamps())
    rotated: list[LinkSigning] = []
    watcher = KeyWatcher(host, "d1", current, rotated.append)
    secret_dir(tmp_path, KEY_B, previous=KEY_A)  # roost keys rotate
    assert sorted(sync_once(source, host / "d1")) == ["key", "previous"]
    assert watcher.check()
    assert (rotated[0].key, rotated[0].previous) == (bytes.fromhex(KEY_B), bytes.fromhex(KEY_A))


def test_an_entry_missing_from_the_secret_keeps_the_handed_key(tmp_path: Path) -> None:
    source = secret_dir(tmp_path, KEY_A)
    target = tmp_path / "host" / "d1"
    sync_once(source, target)
    (source / "key").write_text("")
    assert sync_once(source, target) == []
    assert (target / "key").read_text() == KEY_A


def test_the_loop_syncs_until_stopped_and_never_logs_the_key(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    source = secret_dir(tmp_path, KEY_A, previous=KEY_B)
    target = tmp_path / "host" / "d1"
    stop = threading.Event()
    stop.set()  # one pass, then stop
    with caplog.at_level("DEBUG"):
        run(source, target, None, stop, every_s=0.01)
    assert (target / "key").read_text() == KEY_A
    assert KEY_A not in caplog.text and KEY_B not in caplog.text
    assert "key" in caplog.text


def test_a_failed_pass_is_reported_once_without_key_material(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    source = secret_dir(tmp_path, KEY_A)
    blocker = tmp_path / "host"
    blocker.write_text("not a directory")
    stop = threading.Event()
    stop.set()
    with caplog.at_level("WARNING"):
        run(source, blocker / "d1", None, stop, every_s=0.01)
    assert "cannot hand the signing key over" in caplog.text
    assert KEY_A not in caplog.text


@pytest.mark.parametrize(
    ("text", "owner"), [("65532:65532", (65532, 65532)), ("1000", (1000, 1000))]
)
def test_owner_parses(text: str, owner: tuple[int, int]) -> None:
    assert parse_owner(text) == owner
