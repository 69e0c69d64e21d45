"""roost_kube.events: one Event shape for the operator and the agent."""

from __future__ import annotations

from datetime import UTC, datetime

from roost_kube.events import MESSAGE_LIMIT, event_manifest

VEHICLE = {
    "apiVersion": "roost.dev/v1alpha1",
    "kind": "Vehicle",
    "metadata": {"name": "drone1", "uid": "u1"},
}
MISSION = {
    "apiVersion": "roost.dev/v1alpha1",
    "kind": "Mission",
    "metadata": {"name": "survey", "namespace": "flights", "uid": "u2"},
}
T0 = datetime(2024, 1, 1, tzinfo=UTC)


def test_a_cluster_scoped_objects_event_goes_to_default() -> None:
    event = event_manifest(
        VEHICLE, reason="NodeNotFound", message="m", type="Warning", at=T0, component="op"
    )
    assert event["metadata"]["namespace"] == "default"
    assert event["involvedObject"] == {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "name": "drone1",
        "uid": "u1",
    }
    assert (event["type"], event["reportingComponent"]) == ("Warning", "op")
    assert event["firstTimestamp"] == event["lastTimestamp"] == "2024-01-01T00:00:00Z"
    assert "reportingInstance" not in event


def test_a_namespaced_objects_event_stays_in_its_namespace() -> None:
    event = event_manifest(MISSION, reason="Running", message="m", at=T0, component="op")
    assert event["metadata"]["namespace"] == "flights"
    assert event["involvedObject"]["namespace"] == "flights"
    assert event["type"] == "Normal"


def test_names_are_deterministic_so_a_retried_post_is_a_duplicate() -> None:
    def name(at: datetime | str, message: str = "m") -> str:
        event = event_manifest(VEHICLE, reason="R", message=message, at=at, component="agent")
        return str(event["metadata"]["name"])

    assert name(T0) == name("2024-01-01T00:00:00Z")  # a datetime and its RFC 3339 agree
    assert name(T0) != name(datetime(2024, 1, 1, 0, 0, 1, tzinfo=UTC))
    assert name(T0) != name(T0, "other")
    assert name(T0).startswith("drone1.")


def test_the_agent_names_its_node_and_long_messages_are_cut() -> None:
    event = event_manifest(
        VEHICLE, reason="R", message="x" * 5000, at=T0, component="roost-agent", instance="n1"
    )
    assert event["source"] == {"component": "roost-agent", "host": "n1"}
    assert event["reportingInstance"] == "n1"
    assert len(event["message"]) == MESSAGE_LIMIT
