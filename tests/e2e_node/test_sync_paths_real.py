"""The sync-paths reference mission's own pods on real nodes: the paper's workflow.

The example's unchanged programs and ``mission.yaml`` (sized to the fleet, the followers
given the monitor Service's ClusterIP: the harness has no cluster DNS, see
:mod:`tests.support.realmission`), its image built for amd64 and arm64 as one index,
on real harness nodes: the operator creates a follower pod on each vehicle node and the
monitor pod on the ground node; each follower flies its vehicle's two simulated
autopilots through the Roost agent's hub on the vehicle, lagged on the sandbox's
schedule; the monitor's results (read back from its finished pod's log) are the paper's
Table I, with every corrected transit within 0.5 s of the planned one.

The followers fly the tests' shorter trajectories (``SHORT_TRAJECTORIES``: the example's
shape in 6 s legs of 9 m, from a ConfigMap mounted into the follower pods; the image and
its own 20 s legs are unchanged), and the lag schedule follows those legs: drone-1 about
2 s late at task 1, drone-2 about 1.7 s at task 2, each waited for by the other. Two
vehicles on nodes of this machine's architecture: about 90 s here, the flight (four 6 s
legs plus the delays, take-off and landing) about 45 s of it; with the example's 20 s
legs the test took about 150 s. Not on the emulated
arm64 node: there the follower pod starts (privileged, see ``EMULATED_ONBOARD`` in
:mod:`tests.support.realmission`) and runs the image's arm64 half, but its arm command
through the emulated agent's hub gets no answer within the follower's 3 s, so the
mission never starts (bench/syncpods.py says more).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNodes
from tests.support.images import missing_tools
from tests.support.realfleet import GROUND_NODE
from tests.support.realmission import MissionRun, RealMission
from tests.support.syncrun import SHORT_TRAJECTORIES

# serial: every corrected transit is judged to half a second, and the simulated autopilots
# fly in real time against a 200 ms silence limit; `make e2e` runs this after the rest,
# beside at most one other serial file (Makefile, E2E_SERIAL).
pytestmark = [
    pytest.mark.slow,
    pytest.mark.serial,
    pytest.mark.timeout(3600),  # builds the mission image first when not cached
    pytest.mark.skipif(
        bool(missing_tools()),
        reason=f"image tools not installed: {', '.join(missing_tools())} "
        "(`make images` installs them on Debian)",
    ),
]


@pytest.fixture(scope="module")
def flight(
    cluster: Cluster, real_nodes: RealNodes, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[RealMission, MissionRun]]:
    mission = RealMission(
        cluster, real_nodes, tmp_path_factory.mktemp("sync-real"), trajectories=SHORT_TRAJECTORIES
    )
    try:
        mission.start()
        yield mission, mission.fly()
    finally:
        mission.stop()


def check_flight(mission: RealMission, run: MissionRun) -> None:
    names = [p.name for p in mission.plans]
    # The operator put each follower on its vehicle's node, the monitor on the ground.
    assert run.follower_nodes == {p.name: p.node for p in mission.plans}
    assert run.monitor_node == GROUND_NODE
    # Every vehicle flew every leg; the lags made delays the others waited for.
    assert sorted(run.results) == sorted(names)
    assert all(result["type"] == "done" for result in run.results.values())
    tasks = {
        name: len((mission.trajectory_dir / f"{name}.csv").read_text().splitlines()) - 2
        for name in names
    }
    records = [r for name in names for r in run.results[name]["records"]]
    assert {name: len(run.results[name]["records"]) for name in names} == tasks
    assert max(r["delay_s"] for r in records) > 1.0, "no lag made a delay"
    assert {vehicle for _, vehicle, _ in run.lags_sent} == set(names)
    for record in records:
        assert abs(record["transit_s"] - record["planned_transit_s"]) <= 0.5, record


def test_the_mission_pods_fly_in_sync_on_real_vehicle_nodes(
    flight: tuple[RealMission, MissionRun],
) -> None:
    check_flight(*flight)
