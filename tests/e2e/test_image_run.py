"""The operator and agent images, built by ``make images``, run as the chart runs them.

The OCI archives ``make images`` exports are loaded into a fresh podman image store and
run with a read-only root filesystem and no network: the agent prints its usage, both
run as the non-root uid the chart expects, the modules each entry point needs import
from the image's ahead-of-time bytecode, the agent's per-message path is the compiled
one, and no file in the image keeps a setuid or
setgid bit. Skipped where buildah/podman are not installed (``make images`` installs
them on Debian; other systems need a container engine for ``make e2e-kind`` instead).

The tests run on both platforms of the archives' image indexes: amd64 natively, arm64
under qemu-user-static (docker/binfmt.sh; skipped, saying why, where the kernel refuses),
so the arm64 build's cross-compiled per-message path is imported and run by an arm64
Python. The operator and agent images of one platform are one root filesystem (the
Dockerfile's runtime stage) with another entry point, which
``test_operator_and_agent_images_share_one_root_filesystem`` checks on both platforms; so
under emulation, where every container start costs seconds of qemu, only the agent image
is run: what the emulated operator runs would be the same files (its ``roost_operator``
modules import in ``test_image_modules_import_from_bytecode_on_a_read_only_root``, its
entry point script is there), and what only the runtime decides (the entry point, the
user) is the same on both platforms.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from roost_localcluster.binaries import HOST_ARCH
from tests.support.images import (
    ARCHS,
    Podman,
    archive,
    build_images,
    emulation_missing,
    missing_tools,
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(1800),  # the first test builds the images when they are not cached
    pytest.mark.skipif(
        bool(missing_tools()),
        reason=f"image tools not installed: {', '.join(missing_tools())} "
        "(`make images` installs them on Debian)",
    ),
]

UID = 65532


def operator_run_natively_only(request: pytest.FixtureRequest) -> None:
    """Skip the emulated platform's run of the operator image: it would run the files the
    agent image's emulated tests run (see the module docstring)."""
    arch = request.node.callspec.params["podman"]
    if arch != HOST_ARCH:
        pytest.skip(
            f"{arch} (emulated): the operator image is the agent image's root filesystem "
            "(test_operator_and_agent_images_share_one_root_filesystem), run under emulation "
            "by the agent image's tests"
        )


# Walks the image's root filesystem (there is no find(1) in it) for setuid/setgid files.
SETUID_SCAN = """
import os, stat
dev = os.lstat("/").st_dev
for top, dirs, files in os.walk("/"):
    dirs[:] = [d for d in dirs if os.lstat(os.path.join(top, d)).st_dev == dev]
    for name in files:
        mode = os.lstat(os.path.join(top, name)).st_mode
        if stat.S_ISREG(mode) and mode & (stat.S_ISUID | stat.S_ISGID):
            print(os.path.join(top, name))
"""


@pytest.fixture(scope="module", params=ARCHS)
def podman(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Podman, dict[str, str]]]:
    """A private podman store with both archives' images for one platform loaded:
    (podman, {target: image ID})."""
    arch: str = request.param
    if reason := emulation_missing(arch):
        pytest.skip(f"{arch} programs cannot run here: {reason}")
    images_dir = build_images()
    store = Podman(tmp_path_factory.mktemp(f"podman-{arch}"))
    loaded = {
        target: store.load(archive(images_dir, target), arch) for target in ("operator", "agent")
    }
    for image in loaded.values():
        assert store.inspect(image)["Architecture"] == arch
    yield store, loaded
    store.reset()


def test_agent_image_prints_usage_on_a_read_only_root(
    podman: tuple[Podman, dict[str, str]],
) -> None:
    store, images = podman
    done = store.run(images["agent"], "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: roost-agent"), done.stdout


def test_operator_and_agent_images_share_one_root_filesystem(
    podman: tuple[Podman, dict[str, str]],
) -> None:
    store, images = podman
    operator, agent = (store.inspect(images[target]) for target in ("operator", "agent"))
    assert operator["RootFS"]["Layers"] == agent["RootFS"]["Layers"]
    assert operator["Config"]["User"] == agent["Config"]["User"]
    assert (operator["Config"]["Entrypoint"], agent["Config"]["Entrypoint"]) == (
        ["roost-operator"],
        ["roost-agent"],
    )


def test_operator_image_prints_usage(
    podman: tuple[Podman, dict[str, str]], request: pytest.FixtureRequest
) -> None:
    operator_run_natively_only(request)
    store, images = podman
    done = store.run(images["operator"], "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: roost-operator"), done.stdout


@pytest.mark.parametrize("target", ["operator", "agent"])
def test_image_runs_as_non_root(
    podman: tuple[Podman, dict[str, str]], target: str, request: pytest.FixtureRequest
) -> None:
    if target == "operator":
        operator_run_natively_only(request)
    store, images = podman
    assert store.inspect(images[target])["Config"]["User"] == f"{UID}:{UID}"
    probe = "import os, pwd; print(os.getuid(), os.getgid(), pwd.getpwuid(os.getuid()).pw_name)"
    done = store.run(images[target], "-c", probe, entrypoint="python3")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(UID), str(UID), "roost"]


def test_image_modules_import_from_bytecode_on_a_read_only_root(
    podman: tuple[Podman, dict[str, str]],
) -> None:
    """Everything the entry points import is there, and nothing needs writing: the
    Kubernetes client's watch (which reads return types from docstrings), kopf, the
    MAVLink dialects the agent and the simulator speak."""
    store, images = podman
    probe = (
        "import shutil, sys, roost_agent.main, roost_operator.main, roost_sim.main, kopf;"
        "from kubernetes import watch, client;"
        "w = watch.Watch();"
        "print(w.get_return_type(client.CoreV1Api().list_node).__name__);"
        "print(*(bool(shutil.which(s)) for s in ('roost-operator', 'roost-agent')));"
        "open('/opt/roost/probe', 'w')"
    )
    done = store.run(images["agent"], "-c", probe, entrypoint="python3")
    assert done.stdout.split() == ["V1Node", "True", "True"], done.stdout + done.stderr
    assert "Read-only file system" in done.stderr, done.stderr


def test_agent_image_runs_the_compiled_per_message_path(
    podman: tuple[Podman, dict[str, str]],
) -> None:
    """The modules every MAVLink datagram passes through import as extension modules
    (setup.py compiles them for the image), and the parser works in them."""
    store, images = podman
    probe = (
        "import roost_mavlink.codec as c, roost_agent.health as h;"
        "import roost_agent.transport as t, roost_agent.trust as u;"
        "import roost_agent.reader as r, roost_agent.link as l;"
        "print(*(m.__file__.rsplit('.', 1)[-1] for m in (c, h, t, u, r, l)));"
        "f = c.Encoder(1, 1).encode('HEARTBEAT', type=2, autopilot=12, base_mode=0,"
        " custom_mode=0, system_status=4, mavlink_version=3);"
        "(frame,), used = c.scan(f); print(frame.get_type(), used == len(f))"
    )
    done = store.run(images["agent"], "-c", probe, entrypoint="python3")
    assert done.stdout.split() == ["so"] * 6 + ["HEARTBEAT", "True"], done.stdout + done.stderr


def test_image_has_no_setuid_files(podman: tuple[Podman, dict[str, str]]) -> None:
    store, images = podman
    done = store.run(images["agent"], "-c", SETUID_SCAN, entrypoint="python3")
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""


def test_archives_exist_for_both_targets() -> None:
    images_dir = build_images()
    for target in ("operator", "agent"):
        assert Path(archive(images_dir, target)).stat().st_size > 0
