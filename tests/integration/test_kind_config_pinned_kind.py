"""kind-config.yaml against the real ``kind`` binary of the pinned version, and the KinD
scripts through ``shellcheck``.

KinD loads, decodes and validates the configuration before it touches a container
engine, so ``kind create cluster`` is run with a stand-in ``docker`` on PATH that answers
only the questions KinD asks before validating (``docker -v``, ``docker info``, and
``docker ps`` for existing clusters) and refuses everything else. Reaching the first
refused call, pulling the node image, means KinD accepted the configuration. The stand-in
exists because this machine has no container engine; it is never used to pretend a
cluster runs. The JSON-schema checks are in ``tests/unit/test_repo_kind_config.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from roost_localcluster.binaries import REPO_ROOT
from tests.support.kind import CONFIG, KIND_DIR, kind_config, kind_versions

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
        f"kind {kind_versions()['KIND_VERSION']} "
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
            kind_versions()["KIND_NODE_IMAGE"],
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
    image = kind_versions()["KIND_NODE_IMAGE"]
    provisioning = [call for call in calls if image in call]
    assert provisioning, f"kind stopped before provisioning:\n{output}\ncalls: {calls}"
    assert "invalid" not in output.lower() and "unable to decode" not in output, output


@pytest.mark.slow
def test_pinned_kind_rejects_a_misspelt_field(kind_binary: Path, tmp_path: Path) -> None:
    config = kind_config()
    config["nodes"][1]["extraMount"] = config["nodes"][1].pop("extraMounts")
    path = tmp_path / "broken.yaml"
    path.write_text(yaml.safe_dump(config))
    output, calls = _kind_create(kind_binary, path, tmp_path)
    assert "extraMount" in output, output
    assert not [call for call in calls if kind_versions()["KIND_NODE_IMAGE"] in call], calls


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
