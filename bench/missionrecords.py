"""Mission records: ``records.bundle_ready_s``, Mission end → bundle available.

On the local control plane with ``roost-operator`` running and gathering into a records
directory: three vehicles, each with two autopilots, fly a Mission; each vehicle's
flight is five minutes of MAVLink (both autopilots' frames at 400 Hz each, about the
rate two simulated PX4s send, written with pymavlink's encoder), its decisions and
parameters, laid out with the agent's own manifest code and served by the agent's own
records server (:class:`~roost_agent.records_server.RecordsServer`) on the loopback.
The flights land while the Mission runs; then its workloads complete. The figure is
``status.records.readyTime - status.completionTime`` (both written by the operator):
the first gathering round's start is included, as are listing every vehicle, fetching
and checking every file (sha256), writing the manifest, Events and final status.

Stand-ins, said plainly: the vehicles' status comes from
:class:`~tests.support.fakeagents.FakeAgents` and the flights are synthetic (the real
agent's recorder and a real 5-minute flight are measured on its side); the operator
reaches the records servers directly, not through the API server's pod proxy, which
cannot dial the loopback — in a cluster, add the proxy's hop per request.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

from bench.core import Figure
from roost_agent.records_server import RecordsServer
from roost_api.wellknown import ANNOTATION_RECORDS
from roost_kube.resources import MISSIONS, VEHICLES
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from tests.support.fakeagents import FakeAgents
from tests.support.missionfleet import (
    FLIGHTS,
    Fleet,
    mission_status,
    pods_of,
    release_holds,
    wait_phase,
)
from tests.support.operator import OperatorProcess
from tests.support.tlogs import write_flight as write_tlog_flight
from tests.support.waiting import wait_until
from tests.support.wifilink import land, write_flight

COMMAND = "python -m bench missionrecords"
NAMESPACE = "roost-bench-records"
VEHICLES_N = 3
FLIGHT_S = 300.0
RATE_HZ = 400.0
TIMEOUT_S = 300.0


def _flight_files(tmp: Path, start: float) -> dict[str, bytes]:
    return write_tlog_flight(tmp / "flight", start, duration_s=FLIGHT_S, rate_hz=RATE_HZ)


def run() -> list[Figure]:
    binaries.ensure_built()
    with tempfile.TemporaryDirectory(prefix="bench-records-") as tmp_text:
        tmp = Path(tmp_text)
        bundles = tmp / "bundles"
        armed = datetime.now(UTC).replace(microsecond=0) - timedelta(seconds=FLIGHT_S)
        files = _flight_files(tmp, armed.timestamp())
        with ControlPlane(tmp / "plane") as plane:
            cluster = Cluster.of(plane)
            cluster.install_crds()
            cluster.kubectl("create", "namespace", FLIGHTS)
            operator = OperatorProcess(
                cluster,
                tmp / "operator.log",
                namespace=NAMESPACE,
                environment={"ROOST_RECORDS_DIR": str(bundles)},
            )
            operator.start()
            servers: list[RecordsServer] = []
            try:
                with cluster.kube("roost-bench") as kube, FakeAgents(cluster) as agents:
                    fleet = Fleet(cluster, kube, agents, cluster.add_node)
                    names = fleet.add(VEHICLES_N)
                    flights = {}
                    for name in names:
                        root = tmp / "vehicles" / name
                        flights[name] = write_flight(root, name, armed, files)
                        server = RecordsServer(root, name)
                        servers.append(server)
                        url = f"http://127.0.0.1:{server.port}/"
                        kube.merge_patch(
                            VEHICLES, name, {"metadata": {"annotations": {ANNOTATION_RECORDS: url}}}
                        )
                    mission = fleet.mission("recorded", names=names, count=VEHICLES_N)
                    wait_phase(kube, mission, "Running")
                    landed = datetime.now(UTC)
                    for name in names:
                        land(tmp / "vehicles" / name, flights[name], landed)
                    wait_until(
                        "the onboard pods",  # created right after the Running status
                        lambda: len(pods_of(kube, mission)) == VEHICLES_N,
                        TIMEOUT_S,
                    )
                    release_holds(kube, mission)
                    wait_phase(kube, mission, "Succeeded", TIMEOUT_S)
                    seen_end = time.monotonic()
                    records = wait_until(
                        "the bundle final",
                        lambda: (
                            r
                            if (r := mission_status(kube, mission).get("records"))
                            and r["state"] != "Gathering"
                            else None
                        ),
                        TIMEOUT_S,
                        poll_s=0.05,
                    )
                    polled = time.monotonic() - seen_end
                    status = mission_status(kube, mission)
                    load = os.getloadavg()[0]
                    bundle_bytes = sum(
                        p.stat().st_size
                        for p in (bundles / records["bundle"]).rglob("*")
                        if p.is_file()
                    )
                    kube.delete(MISSIONS, mission, FLIGHTS)
            finally:
                for server in servers:
                    server.close()
                operator.stop()
        shutil.rmtree(bundles, ignore_errors=True)
    end = datetime.fromisoformat(status["completionTime"].replace("Z", "+00:00"))
    ready = datetime.fromisoformat(records["readyTime"].replace("Z", "+00:00"))
    tlog_mb = len(files["hub.tlog"]) / 1e6
    return [
        Figure(
            "records.bundle_ready_s",
            (ready - end).total_seconds(),
            "s",
            "informational",
            COMMAND,
            note=f"Mission end (completionTime) → bundle {records['state']} (readyTime), "
            f"{VEHICLES_N} vehicles x 2 autopilots after a {FLIGHT_S:.0f} s flight each: "
            f"{tlog_mb:.1f} MB tlog per vehicle, {bundle_bytes / 1e6:.1f} MB bundle; the agent's "
            "records server on the loopback (no pod proxy), synthetic flights, stand-in "
            f"status agents; seen by a 50 ms poll {polled:.2f} s after the Succeeded phase; "
            f"1-min load {load:.2f} on {os.cpu_count()} cores",
        )
    ]
