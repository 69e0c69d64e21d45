"""kind-config.yaml is a configuration the pinned KinD accepts.

Two checks. First against a JSON schema of KinD's v1alpha4 configuration
(tests/e2e/kind/kind-config.schema.json, written for Roost from KinD's documented
fields, strict like KinD's decoder). Second against the real ``kind`` binary of the
pinned version (built from its Go module by tests/e2e/kind/install-kind.sh): KinD loads,
decodes and validates the configuration before it touches a container engine, so
``kind create cluster`` is run with a stand-in ``docker`` on PATH that answers only
the two questions KinD asks before validating (``docker -v``, ``docker info``, and
``docker ps`` for existing clusters) and refuses everything else. Reaching the first
refused call, pulling the node image, means KinD accepted the configuration. The
stand-in exists because this machine has no container engine; it is never used to
pretend a cluster runs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from roost_localcluster.binaries import REPO_ROOT

KIND_DIR = REPO_ROOT / "tests" / "e2e" / "kind"
CONFIG = REPO_ROOT / "kind-config.yaml"
SCHEMA = json.loads((KIND_DIR / "kind-config.schema.json").read_text())
VEHICLE_LABEL = "e2e.roost.dev/vehicle"

STAND_IN_DOCKER = """#!/bin/sh
# Stand-in container engine for the KinD config test: answers what KinD asks before
# validating its configuration, records and refuses everything else.
echo "$*" >> "$ROOST_STUB_LOG"
case "$1" in
  -v) echo "Docker version 0.0.0-roost-stand-in, build none" ;;
  info)
    case "$*" in
      *SecurityOptions*) echo "'[]'" ;;
      *) echo '{"CgroupDriver":"systemd","CgroupVersion":"2","MemoryLimit":true,'\
'"PidsLimit":true,"CPUShares":true,"SecurityOptions":[]}' ;;
    esac ;;
  ps) ;;
  *) echo "roost stand-in: no container engine here" >&2; exit 1 ;;
esac
"""


def _versions() -> dict[str, str]:
    pairs = {}
    for line in (KIND_DIR / "versions.env").read_text().splitlines():
        if line and not line.startswith("#"):
            key, _, value = line.partition("=")
            pairs[key] = value
    return pairs


def _config() -> dict[str, Any]:
    config: dict[str, Any] = yaml.safe_load(CONFIG.read_text())
    return config


def _workers() -> list[dict[str, Any]]:
    return [node for node in _config()["nodes"] if node.get("role") == "worker"]


# -- the schema ------------------------------------------------------------------------


def test_kind_config_matches_the_v1alpha4_schema() -> None:
    jsonschema.Draft7Validator.check_schema(SCHEMA)
    jsonschema.validate(_config(), SCHEMA)


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
    config = _config()
    change(config)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(config, SCHEMA)


def test_three_vehicle_workers_with_a_fake_serial_port_and_their_config() -> None:
    workers = _workers()
    assert len(workers) == 3
    roles = [node.get("role", "control-plane") for node in _config()["nodes"]]
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


@pytest.fixture(scope="module")
def kind_binary() -> Path:
    result = subprocess.run(
        [str(KIND_DIR / "install-kind.sh")],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if result.returncode == 3:
        pytest.skip(result.stderr.strip())
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip())
    assert (
        f"kind {_versions()['KIND_VERSION']} "
        in subprocess.run([str(path), "version"], capture_output=True, text=True, check=True).stdout
    )
    return path


def _kind_create(kind: Path, config: Path, tmp_path: Path) -> tuple[str, list[str]]:
    """Run ``kind create cluster`` with the stand-in engine; (kind's output, engine calls)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    docker = bin_dir / "docker"
    docker.write_text(STAND_IN_DOCKER)
    docker.chmod(0o755)
    log = tmp_path / "engine.log"
    env = {key: value for key, value in os.environ.items() if not key.startswith("KIND_")} | {
        "PATH": f"{bin_dir}:{os.environ['PATH']}",
        "ROOST_STUB_LOG": str(log),
    }
    result = subprocess.run(
        [
            str(kind),
            "create",
            "cluster",
            "--config",
            str(config),
            "--image",
            _versions()["KIND_NODE_IMAGE"],
            "--kubeconfig",
            str(tmp_path / "kubeconfig"),
        ],
        check=False,
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0, "the stand-in engine cannot have created a cluster"
    calls = log.read_text().splitlines() if log.exists() else []
    return result.stdout + result.stderr, calls


@pytest.mark.slow
def test_pinned_kind_accepts_kind_config(kind_binary: Path, tmp_path: Path) -> None:
    output, calls = _kind_create(kind_binary, CONFIG, tmp_path)
    image = _versions()["KIND_NODE_IMAGE"]
    provisioning = [call for call in calls if image in call]
    assert provisioning, f"kind stopped before provisioning:\n{output}\ncalls: {calls}"
    assert "invalid" not in output.lower() and "unable to decode" not in output, output


@pytest.mark.slow
def test_pinned_kind_rejects_a_misspelt_field(kind_binary: Path, tmp_path: Path) -> None:
    config = _config()
    config["nodes"][1]["extraMount"] = config["nodes"][1].pop("extraMounts")
    path = tmp_path / "broken.yaml"
    path.write_text(yaml.safe_dump(config))
    output, calls = _kind_create(kind_binary, path, tmp_path)
    assert "extraMount" in output, output
    assert not [call for call in calls if _versions()["KIND_NODE_IMAGE"] in call], calls


# -- the fleet run.sh applies and the scripts ------------------------------------------


def _fleet() -> list[dict[str, Any]]:
    return [doc for doc in yaml.safe_load_all((KIND_DIR / "fleet.yaml").read_text()) if doc]


def test_fleet_declares_the_identity_of_each_workers_host_file() -> None:
    vehicles = [doc for doc in _fleet() if doc["kind"] == "Vehicle"]
    cluster = _config()["name"]
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


@pytest.mark.parametrize("script", ["run.sh", "install-kind.sh", "node-image/build.sh"])
def test_kind_scripts_pass_shellcheck(script: str) -> None:
    shellcheck = Path(sys.executable).parent / "shellcheck"
    result = subprocess.run(
        [str(shellcheck), "--external-sources", str(KIND_DIR / script)],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout + result.stderr


FAILING = "#!/bin/sh\necho 'Cannot connect to the engine at unix:///none' >&2\nexit 1\n"


@pytest.mark.parametrize(
    ("fakes", "env", "reason"),
    [
        # a docker that cannot connect, a podman whose `podman info` fails
        ({"docker": FAILING, "podman": FAILING}, {}, "`podman info` fails"),
        # podman, but not as root
        ({"docker": FAILING, "id": "#!/bin/sh\necho 1000\n"}, {}, "only as root"),
        # docker asked for, but no engine answers
        ({"docker": FAILING}, {"ROOST_KIND_PROVIDER": "docker"}, "no container engine answers"),
    ],
)
def test_run_sh_skips_cleanly_where_it_cannot_run(
    tmp_path: Path, fakes: dict[str, str], env: dict[str, str], reason: str
) -> None:
    """No usable engine: a clear reason, exit status 0, and nothing created."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in fakes.items():
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    result = subprocess.run(
        [str(KIND_DIR / "run.sh")],
        env={**os.environ, **env, "PATH": f"{bin_dir}:{os.environ['PATH']}"},
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "SKIPPED" in result.stdout and reason in result.stdout, result.stdout
