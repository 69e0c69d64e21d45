"""The sync-paths reference mission's own pods on real nodes: the paper's workflow.

The example's unchanged programs and ``mission.yaml`` (sized to the fleet, the followers
given the monitor Service's ClusterIP: the harness has no cluster DNS, see
:mod:`tests.support.realmission`), its image built for amd64 and arm64 as one index,
on real harness nodes: the operator creates a follower pod on each vehicle node and the
monitor pod on the ground node; each follower flies its vehicle's two simulated
autopilots through the Roost agent's hub on the vehicle, lagged on the sandbox's
schedule; the monitor's results (read back from its finished pod's log) are the paper's
Table I, with every corrected transit within 0.5 s of the planned one.

Two fleets: two amd64 vehicles (about 3 minutes here: the flight itself is five 20 s
legs plus the delays, take-off and landing), and three vehicles with the third on the
emulated arm64 node (``arm64_node``: `make e2e-arm64` only; the followers run privileged
there, see ``EMULATED_ONBOARD`` in :mod:`tests.support.realmission`).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNodes
from tests.support.images import emulation_missing, missing_tools
from tests.support.realfleet import GROUND_NODE
from tests.support.realmission import MissionRun, RealMission
from tests.support.syncrun import TRAJECTORIES

HOST = binaries.HOST_ARCH
ARM64 = "arm64"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(3600),  # builds the mission image first when not cached
    pytest.mark.skipif(
        bool(missing_tools()),
        reason=f"image tools not installed: {', '.join(missing_tools())} "
        "(`make images` installs them on Debian)",
    ),
]


def _fly(
    cluster: Cluster,
    pool: RealNodes,
    directory_factory: pytest.TempPathFactory,
    arches: tuple[str, ...],
    wait_s: float,
) -> Iterator[tuple[RealMission, MissionRun]]:
    mission = RealMission(
        cluster, pool, directory_factory.mktemp("sync-real"), arches=arches, wait_s=wait_s
    )
    try:
        mission.start()
        yield mission, mission.fly()
    finally:
        mission.stop()


@pytest.fixture(scope="module")
def amd64_flight(
    cluster: Cluster, real_nodes: RealNodes, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[RealMission, MissionRun]]:
    yield from _fly(cluster, real_nodes, tmp_path_factory, (HOST, HOST), 180.0)


@pytest.fixture(scope="module")
def arm64_flight(
    cluster: Cluster, real_nodes: RealNodes, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[RealMission, MissionRun]]:
    if reason := emulation_missing(ARM64):
        pytest.skip(f"arm64 programs cannot run here: {reason} (docker/binfmt.sh, as root)")
    yield from _fly(cluster, real_nodes, tmp_path_factory, (HOST, HOST, ARM64), 600.0)


def check_flight(mission: RealMission, run: MissionRun) -> None:
    names = [p.name for p in mission.plans]
    # The operator put each follower on its vehicle's node, the monitor on the ground.
    assert run.follower_nodes == {p.name: p.node for p in mission.plans}
    assert run.monitor_node == GROUND_NODE
    # Every vehicle flew every leg; the lags made delays the others waited for.
    assert sorted(run.results) == sorted(names)
    assert all(result["type"] == "done" for result in run.results.values())
    tasks = {
        name: len((TRAJECTORIES / f"{name}.csv").read_text().splitlines()) - 2 for name in names
    }
    records = [r for name in names for r in run.results[name]["records"]]
    assert {name: len(run.results[name]["records"]) for name in names} == tasks
    assert max(r["delay_s"] for r in records) > 1.0, "no lag made a delay"
    assert {vehicle for _, vehicle, _ in run.lags_sent} == set(names)
    for record in records:
        assert abs(record["transit_s"] - record["planned_transit_s"]) <= 0.5, record


def test_two_amd64_vehicles_fly_the_mission_in_sync(
    amd64_flight: tuple[RealMission, MissionRun],
) -> None:
    check_flight(*amd64_flight)


@pytest.mark.arm64_node  # `make e2e-arm64`: minutes under emulation, not in `make test`
def test_three_vehicles_one_on_the_arm64_node_fly_the_mission_in_sync(
    arm64_flight: tuple[RealMission, MissionRun],
) -> None:
    mission, run = arm64_flight
    check_flight(mission, run)
    arm64_node = mission.plans[-1].node
    node = mission.fleet.get("node", arm64_node) if mission.fleet else {}
    assert node["metadata"]["labels"]["kubernetes.io/arch"] == ARM64
