"""Mission claims as Leases (roost_operator.claims): names, manifests, parsing."""

from __future__ import annotations

from datetime import UTC, datetime

from roost_api.meta import ObjectReference
from roost_operator.claims import (
    ANNOTATION_CLAIMED_VEHICLE,
    CLAIM_LABELS,
    Claim,
    claim_lease,
    claim_of,
    claims_by_vehicle,
    holder_of,
    lease_name,
    micro_time,
    release_options,
    takeover_patch,
)

AT = datetime(2026, 5, 1, 12, 0, 0, 123456, tzinfo=UTC)
SURVEY = ObjectReference(namespace="flights", name="survey")


def lease(vehicle: str = "drone-1", holder: str | None = "flights/survey") -> dict[str, object]:
    body = claim_lease(
        vehicle=vehicle,
        vehicle_uid="uid-v",
        holder=SURVEY,
        mission_uid="uid-m",
        namespace="roost-system",
        at=AT,
    )
    body["spec"]["holderIdentity"] = holder
    body["metadata"] |= {"resourceVersion": "42", "uid": "uid-lease"}
    return body


def test_lease_names_are_valid_and_distinct_even_for_the_longest_vehicle_names() -> None:
    assert lease_name("drone-1") == "claim.drone-1"
    long_a, long_b = "a" * 250 + "x", "a" * 250 + "y"
    names = {lease_name(long_a), lease_name(long_b)}
    assert len(names) == 2
    assert all(len(n) <= 253 and n[-1].isalnum() for n in names)


def test_the_claim_lease_is_owned_by_the_vehicle_and_names_the_mission() -> None:
    body = claim_lease(
        vehicle="drone-1",
        vehicle_uid="uid-v",
        holder=SURVEY,
        mission_uid="uid-m",
        namespace="roost-system",
        at=AT,
    )
    meta = body["metadata"]
    assert meta["namespace"] == "roost-system"
    assert meta["labels"] == CLAIM_LABELS
    assert meta["annotations"][ANNOTATION_CLAIMED_VEHICLE] == "drone-1"
    (owner,) = meta["ownerReferences"]
    assert (owner["kind"], owner["name"], owner["uid"]) == ("Vehicle", "drone-1", "uid-v")
    assert body["spec"] == {
        "holderIdentity": "flights/survey",
        "acquireTime": "2026-05-01T12:00:00.123456Z",
    }


def test_a_lease_parses_back_into_the_claim() -> None:
    claim = claim_of(lease())
    assert claim == Claim(
        vehicle="drone-1",
        holder=SURVEY,
        mission_uid="uid-m",
        resource_version="42",
        uid="uid-lease",
    )
    assert claim.holder_key == "flights/survey"


def test_leases_that_record_no_claim_are_ignored() -> None:
    assert claim_of({}) is None
    assert claim_of(lease(holder=None)) is None
    assert claim_of(lease(holder="no-slash")) is None
    assert claims_by_vehicle([lease("a"), lease("b", holder=""), lease("c")]).keys() == {"a", "c"}


def test_holder_identity_is_namespace_slash_name() -> None:
    assert holder_of("flights/survey") == SURVEY
    assert holder_of("/survey") is None
    assert holder_of(None) is None


def test_a_takeover_and_a_release_are_conditional_on_the_version_read() -> None:
    claim = claim_of(lease())
    assert claim is not None
    rival = ObjectReference(namespace="flights", name="rival")
    patch = takeover_patch(claim, rival, "uid-r", AT)
    assert patch["metadata"]["resourceVersion"] == "42"
    assert patch["spec"]["holderIdentity"] == "flights/rival"
    assert release_options(claim)["preconditions"] == {
        "uid": "uid-lease",
        "resourceVersion": "42",
    }
    assert micro_time(AT) == "2026-05-01T12:00:00.123456Z"
