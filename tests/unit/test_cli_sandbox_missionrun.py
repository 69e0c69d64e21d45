"""``roost sandbox up --mission``: which programs run with which environment, and the lag
schedule that creates the delays.

The real monitor and the lag injector's thread are in
``tests/integration/test_cli_sandbox_missionrun_live.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from roost_cli.sandbox import missionrun
from roost_cli.sandbox.missionrun import Lag
from tests.support.realmission import through_cluster_ip, with_trajectories
from tests.support.syncrun import SHORT_TRAJECTORIES

NAMES = ["drone-1", "drone-2", "drone-3"]


def test_unknown_mission_and_missing_trajectory_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown mission 'survey'"):
        missionrun.check("survey", NAMES)
    with pytest.raises(ValueError, match=r"no trajectory for drone-4.*at most 3 vehicles"):
        missionrun.check(missionrun.SYNC_PATHS, [*NAMES, "drone-4"])


def test_followers_reach_their_vehicle_and_the_monitor(tmp_path: Path) -> None:
    connections = {
        name: missionrun.hub_url(f"127.0.0.1:{24550 + i}") for i, name in enumerate(NAMES)
    }
    followers = missionrun.follower_programs(missionrun.SYNC_PATHS, connections, "127.0.0.1:7711")
    assert [f.name for f in followers] == [f"sync-follower-{n}" for n in NAMES]
    first = followers[0].env
    assert first["MAVLINK_URL"] == "udpout:127.0.0.1:24550"
    assert first["SYNC_MONITOR"] == "127.0.0.1:7711"
    assert first["SYNC_VEHICLE"] == "drone-1"
    assert (Path(first["SYNC_TRAJECTORY_DIR"]) / "drone-1.csv").is_file()
    monitor = missionrun.monitor_program(missionrun.SYNC_PATHS, NAMES, tmp_path)
    assert monitor.env["SYNC_VEHICLES"] == "3"
    assert monitor.env["SYNC_OUTPUT"] == str(tmp_path)


def test_a_simulator_report_is_spelled_as_pymavlink_wants_it() -> None:
    assert missionrun.pymavlink_url("udpout://127.0.0.1:15001") == "udpout:127.0.0.1:15001"


def test_the_sandbox_applies_the_missions_own_manifest_sized_to_its_fleet() -> None:
    runtime = {"roost.dev/kwok-runtime": "10m"}
    documents = missionrun.mission_manifests(missionrun.SYNC_PATHS, 2, runtime)
    assert [d["kind"] for d in documents] == ["Mission", "Service"]
    assert missionrun.mission_ref(documents) == ("default", "sync-paths")
    mission = documents[0]["spec"]
    assert mission["vehicles"]["count"] == 2
    assert mission["onFailover"] == "AbortVehicle"
    for workload in ("onboard", "offboard"):
        template = mission[workload]["metadata"]
        assert template["annotations"] == runtime
        assert template["labels"]  # the example's own metadata is kept
    with pytest.raises(ValueError, match="no Mission"):
        missionrun.mission_ref(documents[1:])


@pytest.mark.parametrize(
    ("phase", "out"),
    [
        ("Claimed", False),
        ("Preflight", False),
        ("Running", False),
        ("Succeeded", False),
        ("Aborting", True),
        ("Aborted", True),
        ("Failed", True),
    ],
)
def test_a_follower_stops_when_the_mission_takes_its_vehicle_out(phase: str, out: bool) -> None:
    mission = {"status": {"vehicles": [{"name": "drone-2", "phase": phase}]}}
    assert missionrun.vehicles_out(mission) == ({"drone-2"} if out else set())


def test_a_mission_without_status_has_no_vehicle_out() -> None:
    assert missionrun.vehicles_out({}) == set()
    assert missionrun.vehicles_out({"status": {"vehicles": None}}) == set()


def test_listening_address_is_read_from_the_monitor_log() -> None:
    assert missionrun.listening_address("") is None
    assert missionrun.listening_address("INFO started\nnot json listening\n") is None
    log = 'x\n{"listening": "127.0.0.1:40123"}\n'
    assert missionrun.listening_address(log) == "127.0.0.1:40123"


def test_lag_schedule_follows_the_planned_legs() -> None:
    schedule = missionrun.lag_schedule(("drone-1", "drone-2"))
    assert {lag.vehicle for lag in schedule} == {"drone-1", "drone-2"}  # drone-3 absent
    first = schedule[0]
    planned = 20.0 + missionrun.LAG_OVERRUN_S  # the example's legs: 20 s
    assert first == Lag("drone-1", missionrun.START_DELAY_S, planned, 23.0)
    assert [lag.start_s for lag in schedule] == sorted(lag.start_s for lag in schedule)
    assert all(1 <= lag.percent <= 100 for lag in schedule)


def test_lag_schedule_follows_the_legs_of_other_trajectories(tmp_path: Path) -> None:
    """The tests' shorter trajectories: each lag starts with its leg and lasts it."""
    schedule = missionrun.lag_schedule(("drone-1", "drone-2"), SHORT_TRAJECTORIES)
    start = missionrun.START_DELAY_S
    overrun = missionrun.LAG_OVERRUN_S
    assert [(lag.vehicle, lag.start_s, lag.duration_s) for lag in schedule] == [
        ("drone-1", start, 6.0 + overrun),  # leg 1: 0-6 s
        ("drone-2", start + 6.0, 6.0 + overrun),  # leg 2: 6-12 s
        ("drone-1", start + 18.0, 6.0 + overrun),  # leg 4: 18-24 s
    ]
    # A trajectory without leg 4 gets no lag there; one of uneven legs gets their times.
    (tmp_path / "drone-1.csv").write_text("time_s,north_m,east_m,down_m\n0,0,0,-5\n5,6,0,-5\n")
    (tmp_path / "drone-2.csv").write_text("0,0,0,-5\n4,5,0,-5\n13,5,9,-5\n")
    assert missionrun.lag_schedule(("drone-1", "drone-2"), tmp_path) == (
        Lag("drone-1", start, 5.0 + overrun, 23.0),
        Lag("drone-2", start + 4.0, 9.0 + overrun, 26.0),
    )


def test_a_trajectory_time_that_is_not_a_number_is_refused(tmp_path: Path) -> None:
    (tmp_path / "drone-1.csv").write_text("time_s,north_m,east_m,down_m\n0,0,0,-5\nsoon,1,0,-5\n")
    with pytest.raises(ValueError, match="task time 'soon' is not a number"):
        missionrun.lag_schedule(("drone-1",), tmp_path)


def test_followers_fly_another_trajectory_directory_when_given(tmp_path: Path) -> None:
    connections = {"drone-1": missionrun.hub_url("127.0.0.1:24550")}
    (follower,) = missionrun.follower_programs(
        missionrun.SYNC_PATHS, connections, "127.0.0.1:7711", trajectories=SHORT_TRAJECTORIES
    )
    assert follower.env["SYNC_TRAJECTORY_DIR"] == str(SHORT_TRAJECTORIES)
    with pytest.raises(ValueError, match="no trajectory for drone-1"):
        missionrun.follower_programs(
            missionrun.SYNC_PATHS, connections, "127.0.0.1:7711", trajectories=tmp_path
        )
    with pytest.raises(ValueError, match="is not a directory of trajectories"):
        missionrun.monitor_program(
            missionrun.SYNC_PATHS, ["drone-1"], tmp_path, trajectories=tmp_path / "none"
        )


def test_real_pods_fly_trajectories_from_a_configmap() -> None:
    """The follower pods mount the ConfigMap and are pointed at it; the image is unchanged."""
    documents = with_trajectories(
        missionrun.mission_manifests(missionrun.SYNC_PATHS, 2, {}), SHORT_TRAJECTORIES
    )
    configmap, mission, _ = documents
    assert configmap["kind"] == "ConfigMap"
    assert sorted(configmap["data"]) == ["drone-1.csv", "drone-2.csv", "drone-3.csv"]
    assert configmap["data"]["drone-1.csv"] == (SHORT_TRAJECTORIES / "drone-1.csv").read_text()
    pod = mission["spec"]["onboard"]["spec"]
    (volume,) = pod["volumes"]
    assert volume["configMap"]["name"] == configmap["metadata"]["name"]
    (follower,) = pod["containers"]
    (mount,) = follower["volumeMounts"]
    assert mount["name"] == volume["name"]
    env = {e["name"]: e["value"] for e in follower["env"]}
    assert env["SYNC_TRAJECTORY_DIR"] == mount["mountPath"]
    assert "volumes" not in mission["spec"]["offboard"]["spec"]  # the monitor reads none


def test_the_mission_file_puts_followers_on_the_vehicle_network_and_sizes_the_monitor() -> None:
    documents = missionrun.mission_manifests(missionrun.SYNC_PATHS, 2, {})
    (mission,) = [d for d in documents if d["kind"] == "Mission"]
    onboard = mission["spec"]["onboard"]["spec"]
    # The agent's hub is on the vehicle's loopback; the Service's name resolves there too.
    assert onboard["hostNetwork"] is True
    assert onboard["dnsPolicy"] == "ClusterFirstWithHostNet"
    # The monitor expects the vehicles the Mission got (ROOST_MISSION_VEHICLES), not 3.
    offboard_env = mission["spec"]["offboard"]["spec"]["containers"][0]["env"]
    assert "SYNC_VEHICLES" not in {e["name"] for e in offboard_env}
    assert mission["spec"]["vehicles"]["count"] == 2


def test_followers_reach_the_monitor_through_the_services_cluster_ip() -> None:
    documents = missionrun.mission_manifests(missionrun.SYNC_PATHS, 3, {})
    through_cluster_ip(documents, "10.96.0.42")
    (mission,) = [d for d in documents if d["kind"] == "Mission"]
    (follower,) = mission["spec"]["onboard"]["spec"]["containers"]
    env = {e["name"]: e["value"] for e in follower["env"]}
    assert env["SYNC_MONITOR"] == "10.96.0.42:7700"
