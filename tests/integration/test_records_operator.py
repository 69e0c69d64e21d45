"""Mission records on the real control plane, with ``roost-operator`` as a process.

Each vehicle's records are served by the agent's own records server
(:class:`~roost_agent.records_server.RecordsServer`) over flight directories written
with the agent's manifest code, behind a TCP relay that plays the WiFi link and can
drop (:mod:`tests.support.wifilink`). Each Vehicle's ``roost.dev/records`` annotation
points the operator at its relay, as for agents that run as processes (in a cluster
the operator goes through the API server's pod proxy instead, which refuses to dial
the loopback). The vehicles' status half is :class:`~tests.support.fakeagents.FakeAgents`,
as in :mod:`tests.integration.test_mission_operator`, whose helpers these tests share.

What is checked end to end: the bundle holds exactly the Mission's flights (not an
earlier one), every file with a sha256 that matches its bytes, the Mission's Events and
final state; a transfer cut mid-file resumes with a Range request; a vehicle away at
the end is gathered when it is back; a file whose sha256 does not match is downloaded
again, then named as corrupt (bundle Partial); another bundle on the volume is not
touched; ``roost records get`` fetches the bundle through the operator's records server;
the final bundle is copied to an S3-compatible bucket (moto's server on 127.0.0.1, not
AWS: :mod:`tests.support.s3server`), every object with its sha256;
a Mission that never flew has no record and ``roost records get`` says so, exit 1; an
unusable records volume fails the record with why; with the agents serving on their
vehicles only (the chart's default) the bundle is final in its first round.
About 30 s on two cores (most of it the Vehicles becoming Ready).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from roost_agent.records_server import RecordsServer
from roost_api.mission import MissionPhase, MissionStatus, RecordsState
from roost_api.ports import free_port
from roost_api.records import FlightState
from roost_api.wellknown import ANNOTATION_RECORDS
from roost_kube.client import Kube
from roost_kube.resources import VEHICLES
from roost_localcluster.cluster import Cluster
from roost_operator.records.gather import VehicleTarget, gather_round
from roost_operator.records.planning import gathering
from roost_operator.records.settings import AgentRecords, RecordsSettings
from tests.support.fakeagents import FakeAgents
from tests.support.missionfleet import FLIGHTS, AddNode, Fleet, mission_status, wait_phase
from tests.support.operator import OperatorProcess
from tests.support.s3server import REGION, S3Server, s3_server
from tests.support.waiting import unique, wait_until
from tests.support.wifilink import WifiLink, land, write_flight

pytestmark = pytest.mark.cluster

OPERATOR_NAMESPACE = "roost-it-records"
ROOST = Path(sys.executable).parent / "roost"
WAIT_S = 60.0


@pytest.fixture(scope="module", autouse=True)
def flights_namespace(roost_crds: Cluster) -> None:
    roost_crds.kubectl("create", "namespace", FLIGHTS, check=False)


@pytest.fixture(scope="module")
def records_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("bundles")


@pytest.fixture(scope="module")
def records_port() -> int:
    return free_port()


@pytest.fixture(scope="module")
def bucket(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """An S3-compatible server on 127.0.0.1 (moto's; not AWS) the operator copies to."""
    with s3_server(tmp_path_factory.mktemp("s3") / "server.log") as server:
        yield server


@pytest.fixture(scope="module")
def operator(
    roost_crds: Cluster,
    tmp_path_factory: pytest.TempPathFactory,
    records_dir: Path,
    records_port: int,
    bucket: S3Server,
) -> Iterator[OperatorProcess]:
    secret = bucket.write_credentials(tmp_path_factory.mktemp("records-s3"))
    with OperatorProcess(
        roost_crds,
        tmp_path_factory.mktemp("operator-records") / "operator.log",
        namespace=OPERATOR_NAMESPACE,
        environment={
            "ROOST_RECORDS_DIR": str(records_dir),
            "ROOST_RECORDS_PORT": str(records_port),
            "ROOST_RECORDS_RETRY_SECONDS": "1",
            "ROOST_RECORDS_S3_ENDPOINT": bucket.endpoint,
            "ROOST_RECORDS_S3_BUCKET": bucket.bucket,
            "ROOST_RECORDS_S3_REGION": REGION,
            "ROOST_RECORDS_S3_PREFIX": "roost",
            "ROOST_RECORDS_S3_CREDENTIALS_DIR": str(secret),
        },
    ) as proc:
        yield proc


@pytest.fixture
def fleet(
    roost_crds: Cluster, operator: OperatorProcess, kube: Kube, fake_nodes: AddNode
) -> Iterator[Fleet]:
    with FakeAgents(roost_crds) as agents:
        created = Fleet(roost_crds, kube, agents, fake_nodes)
        yield created
        created.cleanup()


def records_of(kube: Kube, name: str) -> dict[str, Any]:
    records: dict[str, Any] = mission_status(kube, name).get("records") or {}
    return records


def per_vehicle(records: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {v["name"]: v for v in records.get("vehicles") or []}


def wait_records(kube: Kube, name: str, what: str, check: Any) -> dict[str, Any]:
    def ready() -> dict[str, Any] | None:
        records = records_of(kube, name)
        return records if records and check(records) else None

    try:
        found: dict[str, Any] = wait_until(f"mission {name}: {what}", ready, WAIT_S)
    except TimeoutError as error:
        raise AssertionError(
            f"{error}; records now: {json.dumps(records_of(kube, name))}"
        ) from error
    return found


def roost(cluster: Cluster, home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HOME": str(home), "KUBECONFIG": str(cluster.kubeconfig)}
    return subprocess.run(
        [str(ROOST), *args], capture_output=True, text=True, env=env, timeout=120, check=False
    )


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_missions_record_survives_a_cut_a_vehicle_away_and_a_corrupt_file(
    *,
    fleet: Fleet,
    bucket: S3Server,
    kube: Kube,
    roost_crds: Cluster,
    records_dir: Path,
    records_port: int,
    tmp_path: Path,
) -> None:
    a, b, c = fleet.add(3)
    armed = datetime.now(UTC).replace(microsecond=0) - timedelta(seconds=2)
    tlog = os.urandom(300_000)
    servers: dict[str, RecordsServer] = {}
    links: dict[str, WifiLink] = {}
    flights: dict[str, str] = {}
    for vehicle in (a, b, c):
        directory = tmp_path / "vehicles" / vehicle
        earlier = armed - timedelta(hours=1)
        write_flight(directory, vehicle, earlier, {"hub.tlog": b"old"}, state=FlightState.COMPLETE,
                     disarmed_at=earlier + timedelta(minutes=5))  # fmt: skip
        flights[vehicle] = write_flight(
            directory,
            vehicle,
            armed,
            {
                "hub.tlog": tlog,
                "decisions.jsonl": b'{"event": "armed"}\n',
                "params/ap1.json": b'{"SYSID_THISMAV": 1}',
            },
            corrupt=frozenset({"decisions.jsonl"}) if vehicle == c else frozenset(),
        )
        servers[vehicle] = RecordsServer(directory, vehicle)
        links[vehicle] = WifiLink(servers[vehicle].port).up()
        kube.merge_patch(
            VEHICLES,
            vehicle,
            {"metadata": {"annotations": {ANNOTATION_RECORDS: links[vehicle].url}}},
        )
    other = records_dir / "elsewhere_older_00000000"
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps({"readyAt": armed.isoformat(), "files": []}))
    before = sha256(other / "manifest.json")
    try:
        name = fleet.mission(unique("recorded"), names=[a, b, c], count=3, hold=False)
        wait_phase(kube, name, "Succeeded")
        links[a].cut_after(100_000)  # a's link drops in the middle of its tlog
        # Still armed: gathering waits for the flights to end.
        waiting = wait_records(
            kube, name, "waiting for the flights",
            lambda r: "waiting" in (per_vehicle(r).get(a, {}).get("message") or ""),
        )  # fmt: skip
        assert waiting["state"] == "Gathering"
        links[b].down()  # b's WiFi drops before it lands
        landed = datetime.now(UTC)
        for vehicle in (a, b, c):
            land(tmp_path / "vehicles" / vehicle, flights[vehicle], landed)
        away = wait_records(
            kube, name, "a and c gathered, b pending",
            lambda r: per_vehicle(r)[a]["state"] == "Complete"
            and per_vehicle(r)[c]["state"] == "Partial"
            and "unreachable" in (per_vehicle(r)[b].get("message") or ""),
        )  # fmt: skip
        assert away["state"] == "Gathering" and "pending: " + b in away["message"]
        links[b].up()  # back in range
        final = wait_records(kube, name, "the record final", lambda r: r["state"] != "Gathering")
    finally:
        for vehicle, server in servers.items():
            links[vehicle].down()
            server.close()

    assert final["state"] == "Partial", final
    assert {v: s["state"] for v, s in per_vehicle(final).items()} == {
        a: "Complete", b: "Complete", c: "Partial"
    }  # fmt: skip
    assert "sha256" in per_vehicle(final)[c]["message"]
    assert final["readyTime"]
    assert links[a].cuts == 1, "the tlog transfer was cut once (and resumed: it is whole)"

    bundle = records_dir / final["bundle"]
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["state"] == "Partial"
    assert sorted(f["flightId"] for f in manifest["flights"]) == sorted(flights.values())
    for entry in manifest["files"]:
        assert sha256(bundle / entry["path"]) == entry["sha256"], entry["path"]
    paths = {e["path"] for e in manifest["files"]}
    assert {"mission.json", "events.json", f"vehicles/{a}/{flights[a]}/hub.tlog"} <= paths
    assert (bundle / f"vehicles/{a}/{flights[a]}/hub.tlog").read_bytes() == tlog
    assert f"vehicles/{c}/{flights[c]}/decisions.jsonl" not in paths
    assert [(m["vehicle"], m.get("path")) for m in manifest["missing"]] == [(c, "decisions.jsonl")]
    assert "after 3 downloads" in manifest["missing"][0]["reason"]
    assert not list(bundle.rglob("*.part"))
    events = json.loads((bundle / "events.json").read_text())
    assert "Started" in [e["reason"] for e in events], events  # its phase transitions
    assert json.loads((bundle / "mission.json").read_text())["status"]["phase"] == "Succeeded"
    assert sha256(other / "manifest.json") == before, "another bundle was touched"

    with urllib.request.urlopen(f"http://127.0.0.1:{records_port}/bundles", timeout=10) as answer:
        listed = json.load(answer)["bundles"]
    assert final["bundle"] in [entry["bundle"] for entry in listed]

    listing = roost(roost_crds, tmp_path, "records", "list", "-n", FLIGHTS, "-o", "json")
    assert listing.returncode == 0, listing.stderr
    assert {"mission": name, "records": "Partial"}.items() <= next(
        row for row in json.loads(listing.stdout) if row["mission"] == name
    ).items()
    out = tmp_path / "fetched"
    got = roost(
        roost_crds, tmp_path, "records", "get", f"mission/{FLIGHTS}/{name}", "-o", str(out),
        "--records-url", f"http://127.0.0.1:{records_port}",
    )  # fmt: skip
    assert got.returncode == 0, got.stderr
    assert "missing:" in got.stdout and "decisions.jsonl" in got.stdout
    for entry in manifest["files"]:
        assert sha256(out / entry["path"]) == entry["sha256"]

    # The final bundle is copied to the bucket, the manifest with it.
    uploaded = wait_records(
        kube, name, "the bundle in the bucket",
        lambda r: (r.get("upload") or {}).get("state") == "Complete",
    )["upload"]  # fmt: skip
    assert uploaded["location"] == f"s3://{bucket.bucket}/roost/{final['bundle']}/"
    objects = bucket.objects()
    prefix = f"roost/{final['bundle']}/"
    assert objects[prefix + "manifest.json"] == (bundle / "manifest.json").read_bytes()
    for entry in manifest["files"]:
        assert hashlib.sha256(objects[prefix + entry["path"]]).hexdigest() == entry["sha256"]
    assert uploaded["objects"] == len(manifest["files"]) + 1


def test_a_mission_that_never_flew_has_no_record_and_get_says_so(
    fleet: Fleet, kube: Kube, roost_crds: Cluster, records_port: int, tmp_path: Path
) -> None:
    (vehicle,) = fleet.add(1)
    name = fleet.mission(unique("grounded"), names=[vehicle], count=1, abort=True)
    status = wait_phase(kube, name, "Aborted")
    assert "records" not in status
    got = roost(
        roost_crds, tmp_path, "records", "get", f"mission/{FLIGHTS}/{name}", "-o",
        str(tmp_path / "out"), "--records-url", f"http://127.0.0.1:{records_port}",
    )  # fmt: skip
    assert got.returncode == 1
    assert "never flew" in got.stderr and "Traceback" not in got.stderr
    assert not (tmp_path / "out").exists()


def test_an_unusable_records_volume_fails_the_record_once_with_why(
    kube: Kube, tmp_path: Path
) -> None:
    """The volume is a file, not a directory: the round ends Failed (final, so the
    Mission is not looked at again) with the volume's error, without contacting any vehicle."""
    (tmp_path / "volume").write_text("not a directory")
    status = MissionStatus(
        phase=MissionPhase.SUCCEEDED,
        start_time=datetime.now(UTC) - timedelta(minutes=5),
        completion_time=datetime.now(UTC),
        records=gathering("flights_x_00000000", ["a"]),
    )
    result = gather_round(
        kube,
        RecordsSettings(directory=tmp_path / "volume"),
        namespace=FLIGHTS,
        name="x",
        uid="0",
        status=status,
        vehicles=[VehicleTarget("a", "a-node", {ANNOTATION_RECORDS: "http://127.0.0.1:9/"})],
        now=datetime.now(UTC),
    )
    assert result.state == RecordsState.FAILED and RecordsState(result.state).final
    assert "records volume" in (result.message or "")


def test_agents_serving_on_the_vehicle_only_give_a_final_bundle_at_once(
    kube: Kube, tmp_path: Path
) -> None:
    """The chart's default (``ROOST_RECORDS_AGENTS=on-vehicle``): the first round writes
    the bundle from what the operator holds and it is final, each vehicle saying where its
    flights are; no vehicle is contacted (the one with a records URL on a closed port
    would otherwise be Pending, a deleted one "unreachable")."""
    status = MissionStatus(
        phase=MissionPhase.SUCCEEDED,
        start_time=datetime.now(UTC) - timedelta(minutes=5),
        completion_time=datetime.now(UTC),
        records=gathering("flights_y_00000000", ["a", "gone"]),
    )
    now = datetime.now(UTC)
    result = gather_round(
        kube,
        RecordsSettings(directory=tmp_path, agents=AgentRecords.ON_VEHICLE),
        namespace=FLIGHTS,
        name="y",
        uid="1",
        status=status,
        vehicles=[VehicleTarget("a", "a-node", {}), VehicleTarget("gone")],
        now=now,
    )
    assert result.state == RecordsState.PARTIAL and result.ready_time == now
    assert [(v.name, v.state) for v in result.vehicles] == [
        ("a", "OnVehicle"),
        ("gone", "OnVehicle"),
    ]
    assert "agent.records.bindNodeAddress: true" in (result.vehicles[0].message or "")
    bundle = tmp_path / "flights_y_00000000"
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["state"] == "Partial" and manifest["flights"] == []
    assert {m["vehicle"] for m in manifest["missing"]} == {"a", "gone"}
    assert (bundle / "mission.json").exists() and (bundle / "events.json").exists()
