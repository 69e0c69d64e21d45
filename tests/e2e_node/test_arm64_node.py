"""The chart's agent on an arm64 vehicle node: a Raspberry Pi's programs under emulation.

The vehicle node's kubelet, kube-proxy, containerd and the CNI plugins are built for
arm64 (``localcluster/build-node.sh --arch arm64``) and run here as arm64 programs under
Debian's qemu-user-static through the kernel's binfmt_misc (``docker/binfmt.sh``); so
the kubelet itself reports ``kubernetes.io/arch=arm64`` (nothing sets the label). The
agent DaemonSet pod scheduled there runs the arm64 build of the agent image from the
same image index the amd64 ground node's operator pod comes from, an arm64 program under
the same emulation. runc and its shim are the host's: the arm64 ones cannot start
containers under qemu-user (docs/real-node.md says why). The simulated autopilots stay
programs of this machine in the vehicle node's network namespace: they are the flight
controllers, not the companion computer.

Same steps as tests/e2e_node/test_chart_real.py's first half: the agent's report of both
autopilots healthy, then a failover when the active one is silenced. Skipped, saying why,
where arm64 programs cannot run (no binfmt_misc, or the kernel refuses the interpreter).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNodes
from roost_sim.faults import FaultKind
from tests.support.images import emulation_missing, missing_tools
from tests.support.realfleet import EMULATED_NODE_AGENT, RealFleet
from tests.support.waiting import wait_until

ARCH = "arm64"
# Everything on the vehicle node runs about ten times slower under emulation.
WAIT_S = 600.0


pytestmark = [
    pytest.mark.slow,
    pytest.mark.arm64_node,  # `make e2e-arm64`: minutes under emulation, not in `make test`
    pytest.mark.timeout(3600),  # builds the arm64 node programs first when not cached
    pytest.mark.skipif(
        bool(missing_tools()),
        reason=f"image tools not installed: {', '.join(missing_tools())} "
        "(`make images` installs them on Debian)",
    ),
    pytest.mark.skipif(
        bool(emulation_missing(ARCH)),
        reason=f"arm64 programs cannot run here: {emulation_missing(ARCH)} "
        "(docker/binfmt.sh sets it up, as root)",
    ),
]


@pytest.fixture(scope="module")
def fleet(
    cluster: Cluster, real_nodes: RealNodes, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[RealFleet]:
    running = RealFleet(
        cluster,
        real_nodes,
        tmp_path_factory.mktemp("arm64-fleet"),
        release="pi",
        namespace="roost-pi",
        vehicle_arch=ARCH,
        wait_s=WAIT_S,
        agent_values=EMULATED_NODE_AGENT,
    )
    try:
        running.start()
        yield running
    finally:
        running.stop()


def test_vehicle_node_is_arm64_by_its_own_kubelet(fleet: RealFleet) -> None:
    assert fleet.vehicle_node is not None
    node = fleet.get("node", fleet.vehicle_node.name)
    assert node["metadata"]["labels"]["kubernetes.io/arch"] == ARCH
    assert node["status"]["nodeInfo"]["architecture"] == ARCH
    assert fleet.ground is not None
    ground = fleet.get("node", fleet.ground.name)
    assert ground["metadata"]["labels"]["kubernetes.io/arch"] == "amd64"
    # The programs behind it are arm64 executables (ELF machine 183, AArch64).
    kubelet = fleet.vehicle_node.processes["kubelet"]
    executable = kubelet.argv[kubelet.argv.index("--") + 1]
    header = Path(executable).read_bytes()[:20]
    assert header[:4] == b"\x7fELF" and int.from_bytes(header[18:20], "little") == 183


def test_agent_pod_runs_the_arm64_image(fleet: RealFleet) -> None:
    pod = fleet.agent_pod()
    assert pod is not None and pod["status"]["phase"] == "Running"
    machine = fleet.cluster.kubectl(
        "exec", pod["metadata"]["name"], "-n", fleet.namespace, "--",
        "python3", "-c", "import platform; print(platform.machine())",
    ).stdout.strip()  # fmt: skip
    assert machine == "aarch64"


def test_agent_reports_both_autopilots_healthy(fleet: RealFleet) -> None:
    assert fleet.reported()
    assert fleet.autopilot_status()["activeAutopilot"] == "px4-a"


def test_silenced_autopilot_fails_over(fleet: RealFleet) -> None:
    # In flight, as tests/e2e_node/test_chart_real.py silences it (on the ground a
    # silent autopilot is reported STALE without a switch).
    fleet.fly()
    wait_until(
        "the vehicle airborne",
        lambda: all(a.get("armed") for a in fleet.autopilot_status().get("autopilots", [])),
        WAIT_S,
    )
    answer = fleet.control("px4-a", {"op": "fault", "kind": FaultKind.SILENCE.value, "value": None})
    assert answer.get("ok"), answer
    wait_until(
        "the failover to px4-b",
        lambda: fleet.autopilot_status().get("activeAutopilot") == "px4-b",
        WAIT_S,
    )
    last = fleet.autopilot_status()["lastFailover"]
    assert (last["from"], last["to"], last["trigger"]) == ("px4-a", "px4-b", "Automatic")
