"""A scripted flight against the real control plane with ``roost-operator`` running: what
the cluster may and may not change under a vehicle in the air.

The node agent's report is the one stand-in: the script writes the RedundantAutopilot's
status as an agent would (an autopilot armed, then disarmed); everything else is real —
kube-apiserver, the disruption controller of kube-controller-manager, kwok running the
vehicle's pods on its fake node, ``kubectl drain`` and the Eviction API. Shared by the
integration test (``tests/integration/test_vehicle_operator.py``) and ``bench
disruption``.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass

from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.patches import Obj
from roost_kube.resources import PODDISRUPTIONBUDGETS, PODS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_localcluster.cluster import Cluster
from roost_operator.vehicles.manifests import is_component_pod
from tests.support.waiting import wait_until

DRAIN_TIMEOUT = "10s"
REQUEST_TIMEOUT = "3s"
"""kubectl's client waits out the Retry-After (10 s) of every eviction the API server
refuses, ten times over, before its drain sees the refusal: a refused drain took about
100 s whatever ``--timeout`` said. Bounding each request ends the drain after the first
refusal; the refusal's own words come from one Eviction per pod (:func:`_evict`)."""


@dataclass
class FlightOutcome:
    """What happened to the vehicle's pods and node over the flight."""

    drain_in_flight: subprocess.CompletedProcess[str]
    evictions_in_flight: dict[str, str]  # pod name -> the API server's answer
    replacements_in_flight: int
    deferred: list[str]
    hold_reason: str
    drain_after_landing: subprocess.CompletedProcess[str]
    replaced_after_landing: bool
    budget_left: bool


def autopilot_report(names: list[str], *, armed: bool) -> str:
    """A RedundantAutopilot status patch as the agent writes it (every autopilot armed or
    disarmed, the first active)."""
    landed = "InAir" if armed else "OnGround"
    healths = [{"name": n, "level": "OK", "armed": armed, "landedState": landed} for n in names]
    return json.dumps({"status": {"activeAutopilot": names[0], "autopilots": healths}})


def _pod_uids(kube: Kube, vehicle: str, namespace: str) -> dict[str, str]:
    pods = kube.list_objects(PODS, namespace=namespace, labels={"roost.dev/vehicle": vehicle})
    return {
        p["metadata"]["name"]: p["metadata"]["uid"]
        for p in pods
        if is_component_pod(p) and not p["metadata"].get("deletionTimestamp")
    }


def _hold(kube: Kube, vehicle: str) -> Obj | None:
    hold: Obj | None = ((kube.get(VEHICLES, vehicle) or {}).get("status") or {}).get("flightHold")
    return hold


def _drain(cluster: Cluster, node: str) -> subprocess.CompletedProcess[str]:
    return cluster.kubectl(
        "drain",
        node,
        "--ignore-daemonsets",
        "--delete-emptydir-data",
        f"--timeout={DRAIN_TIMEOUT}",
        f"--request-timeout={REQUEST_TIMEOUT}",
        check=False,
    )


def _evict(kube: Kube, pods: list[str], namespace: str) -> dict[str, str]:
    """Ask the Eviction API, once, to evict each pod (as a drain does): the answer per pod,
    "evicted" or the refusal's message."""
    answers: dict[str, str] = {}
    for name in pods:
        eviction = {
            "apiVersion": "policy/v1",
            "kind": "Eviction",
            "metadata": {"name": name, "namespace": namespace},
        }
        path = f"{PODS.object_path(name, namespace)}/eviction"
        try:
            kube.request("POST", path, body=eviction)
            answers[name] = "evicted"
        except ApiError as refused:
            answers[name] = refused.message
    return answers


def fly_change_and_drain(
    cluster: Cluster, kube: Kube, *, vehicle: str, node: str, namespace: str
) -> FlightOutcome:
    """The vehicle (running and Ready, with a RedundantAutopilot of autopilots fc-a and
    fc-b) takes off, gets a config change, its node is drained; it lands, the node is
    drained again."""
    patch_status = ("patch", "redundantautopilot", vehicle, "--subresource=status", "--type=merge")
    spec = (kube.get(REDUNDANT_AUTOPILOTS, vehicle) or {})["spec"]
    names = [a["name"] for a in spec["autopilots"]]
    before = _pod_uids(kube, vehicle, namespace)
    cluster.kubectl(*patch_status, "-p", autopilot_report(names, armed=True))
    budget = f"roost-vehicle-{vehicle}-in-flight"
    wait_until("the in-flight budget", lambda: kube.get(PODDISRUPTIONBUDGETS, budget, namespace))
    change = json.dumps({"spec": {"config": {"IN_FLIGHT_CHANGE": "1"}}})
    cluster.kubectl("patch", "vehicle", vehicle, "--type=merge", "-p", change)
    hold = wait_until(
        "the replacement to be deferred", lambda: (_hold(kube, vehicle) or {}).get("deferred")
    )
    drained = _drain(cluster, node)
    evictions = _evict(kube, sorted(before), namespace)
    during = _pod_uids(kube, vehicle, namespace)
    replacements = sum(1 for name, uid in before.items() if during.get(name) != uid)
    reason = (_hold(kube, vehicle) or {}).get("reason", "")
    cluster.kubectl("uncordon", node)

    cluster.kubectl(*patch_status, "-p", autopilot_report(names, armed=False))
    wait_until("the hold to be released", lambda: _hold(kube, vehicle) is None)
    replaced = wait_until(
        "the deferred replacement after landing",
        lambda: any(
            _pod_uids(kube, vehicle, namespace).get(n) not in (None, u) for n, u in before.items()
        ),
    )
    after = _drain(cluster, node)
    cluster.kubectl("uncordon", node)
    return FlightOutcome(
        drain_in_flight=drained,
        evictions_in_flight=evictions,
        replacements_in_flight=replacements,
        deferred=list(hold),
        hold_reason=str(reason),
        drain_after_landing=after,
        replaced_after_landing=bool(replaced),
        budget_left=kube.get(PODDISRUPTIONBUDGETS, budget, namespace) is not None,
    )
