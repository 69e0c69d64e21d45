"""The Jobs a Mission runs (roost_operator.missions.workloads): onboard Jobs pinned to
their vehicle, the offboard Job kept off vehicles, template probes and bounded names.

Every input is an API model built as the API server would return it
(:mod:`tests.support.missions`); the functions under test are pure: no mocks.
"""

from __future__ import annotations

from roost_api.wellknown import (
    LABEL_VEHICLE,
    TAINT_VEHICLE,
)
from roost_operator.missions.machine import (
    plan_mission,
)
from roost_operator.missions.workloads import (
    ENV_MISSION_VEHICLE_INDEX,
    ENV_MISSION_VEHICLES,
    bounded_name,
    offboard_job_name,
    onboard_job_name,
    template_probes,
)
from tests.support.missions import (
    ME,
    claimed,
    mission_spec,
    observe,
)


def test_an_onboard_job_is_pinned_tolerated_configured_and_knows_its_peers() -> None:
    plan = plan_mission(observe(claimed("a", "b"), spec=mission_spec(backoffLimit=4)))
    manifest = plan.jobs_to_create[1]
    assert manifest["spec"]["backoffLimit"] == 4
    assert manifest["metadata"]["ownerReferences"][0]["uid"] == ME.uid
    pod = manifest["spec"]["template"]["spec"]
    assert pod["restartPolicy"] == "Never"
    assert pod["nodeSelector"] == {LABEL_VEHICLE: "b"}
    assert any(t["key"] == TAINT_VEHICLE and t["value"] == "b" for t in pod["tolerations"])
    container = pod["containers"][0]
    mounts = {m["mountPath"] for m in container["volumeMounts"]}
    assert mounts == {"/etc/roost", "/etc/starling"}
    env = {e["name"]: e.get("value", e.get("valueFrom")) for e in container["env"]}
    assert env[ENV_MISSION_VEHICLES] == "a,b"
    assert env[ENV_MISSION_VEHICLE_INDEX] == "1"
    assert env["MINE"] == "1"
    assert env["VEHICLE_NAME"] == {
        "configMapKeyRef": {"name": "roost-vehicle-b", "key": "VEHICLE_NAME"}
    }
    assert manifest["spec"]["template"]["metadata"]["labels"]["app"] == "controller"


def test_the_offboard_job_is_kept_off_vehicle_nodes() -> None:
    spec = mission_spec(offboard={"spec": {"containers": [{"name": "m", "image": "monitor"}]}})
    offboard = plan_mission(observe(claimed("a", "b"), spec=spec)).jobs_to_create[-1]
    pod = offboard["spec"]["template"]["spec"]
    terms = pod["affinity"]["nodeAffinity"]["requiredDuringSchedulingIgnoredDuringExecution"][
        "nodeSelectorTerms"
    ]
    assert terms == [{"matchExpressions": [{"key": LABEL_VEHICLE, "operator": "DoesNotExist"}]}]
    assert "tolerations" not in pod and "nodeSelector" not in pod
    assert {"name": ENV_MISSION_VEHICLES, "value": "a,b"} in pod["containers"][0]["env"]


def test_the_template_probes_are_the_jobs_the_mission_would_create() -> None:
    """What is dry-run before claiming is exactly what would be created after it."""
    spec = mission_spec(
        vehicles={"names": ["a", "b"], "count": 2},
        offboard={"spec": {"containers": [{"name": "m", "image": "monitor"}]}},
    )
    obs = observe(claimed("a", "b"), spec=spec)
    probes = template_probes(
        mission=ME, spec=spec, vehicles=["a", "b"], config_values=obs.config_values
    )
    assert [field for field, _ in probes] == ["spec.onboard", "spec.offboard"]
    created = {j["metadata"]["name"]: j for j in plan_mission(obs).jobs_to_create}
    for _, probe in probes:
        assert probe == created[probe["metadata"]["name"]]
    onboard_only = template_probes(
        mission=ME, spec=mission_spec(), vehicles=["a"], config_values={}
    )
    assert [field for field, _ in onboard_only] == ["spec.onboard"]
    assert template_probes(mission=ME, spec=spec, vehicles=[], config_values={}) == []


def test_long_names_are_bounded_and_stay_distinct() -> None:
    first = onboard_job_name("m" * 40, "vehicle-" + "x" * 30 + "-1")
    second = onboard_job_name("m" * 40, "vehicle-" + "x" * 30 + "-2")
    assert len(first) <= 63 and len(second) <= 63 and first != second
    assert bounded_name("short", "name") == "short-name"
    assert offboard_job_name("m") == "m-offboard"
