"""What to do about a component's live Pod, its readiness, and removing a gone Vehicle's
pods, decided without a cluster."""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.wellknown import (
    ANNOTATION_POD_HASH,
    LABEL_NODE,
)
from roost_operator.vehicles.pods import (
    PodStep,
    ReleaseStep,
    pod_node,
    pod_state,
    pod_step,
    release_step,
)

# -- replacing pods --------------------------------------------------------------------

DESIRED: dict[str, Any] = {"metadata": {"annotations": {ANNOTATION_POD_HASH: "new"}}}


def live_pod(
    hash_: str = "new", phase: str = "Running", *, deleting: bool = False
) -> dict[str, Any]:
    meta: dict[str, Any] = {"annotations": {ANNOTATION_POD_HASH: hash_}}
    if deleting:
        meta["deletionTimestamp"] = "2024-01-01T00:00:00Z"
    return {"metadata": meta, "status": {"phase": phase}}


@pytest.mark.parametrize(
    ("live", "node_exists", "step"),
    [
        # no pod: create it, once its node exists
        (None, True, PodStep.CREATE),
        (None, False, PodStep.WAIT),
        # the desired pod: keep it, whatever its phase short of an end
        (live_pod(), True, PodStep.KEEP),
        (live_pod(phase="Pending"), True, PodStep.KEEP),
        (live_pod(), False, PodStep.KEEP),
        # an outdated pod: delete it first (its successor follows its deletion)
        (live_pod("old"), True, PodStep.REPLACE),
        (live_pod("old", "Failed"), True, PodStep.REPLACE),
        ({"metadata": {}, "status": {"phase": "Running"}}, True, PodStep.REPLACE),
        # an ended pod (evicted, failed, succeeded): delete it, then recreate it
        (live_pod(phase="Failed"), True, PodStep.RESTART),
        (live_pod(phase="Succeeded"), True, PodStep.RESTART),
        # a pod on its way out: never a second one beside it
        (live_pod(deleting=True), True, PodStep.WAIT),
        (live_pod("old", deleting=True), True, PodStep.WAIT),
        (live_pod(phase="Failed", deleting=True), True, PodStep.WAIT),
    ],
)
def test_pod_replacement_decision_table(
    live: dict[str, Any] | None, node_exists: bool, step: PodStep
) -> None:
    assert pod_step(live, DESIRED, node_exists=node_exists) is step


# -- readiness and conditions --------------------------------------------------------


def pod(
    phase: str = "Running", ready: str = "True", hash_: str = "new", *, deleting: bool = False
) -> dict[str, Any]:
    body = live_pod(hash_, phase, deleting=deleting)
    body["status"]["conditions"] = [{"type": "Ready", "status": ready}]
    return body


@pytest.mark.parametrize(
    ("live", "ready", "detail"),
    [
        (None, False, "does not exist"),
        (pod(deleting=True), False, "terminating"),
        (pod(hash_="old"), False, "outdated"),
        (pod("Pending", "False"), False, "Pending"),
        (pod("Failed", "False"), False, "ended (Failed"),
        (pod("Running", "False"), False, "not Ready"),
        (pod(), True, ""),
    ],
)
def test_pod_state_says_what_is_missing(
    live: dict[str, Any] | None, ready: bool, detail: str
) -> None:
    state = pod_state("mavros", live, "new")
    assert state.ready is ready
    assert detail in state.detail
    assert bool(state.detail) is not ready


def test_pod_state_names_a_container_that_cannot_start() -> None:
    live = pod("Pending", "False")
    live["status"]["containerStatuses"] = [
        {"state": {"waiting": {"reason": "ImagePullBackOff", "message": "no such image"}}}
    ]
    assert "ImagePullBackOff: no such image" in pod_state("mavros", live, "new").detail


# -- releasing a gone Vehicle's pods -------------------------------------------------------


def _node(ready: str) -> dict[str, Any]:
    return {"status": {"conditions": [{"type": "Ready", "status": ready}]}}


@pytest.mark.parametrize(
    ("terminating", "node", "step"),
    [
        # pod terminating  its node           → step
        (False, _node("True"), ReleaseStep.DELETE),
        (True, _node("True"), ReleaseStep.LEAVE),  # its kubelet is finishing it
        (False, _node("False"), ReleaseStep.DELETE),  # NotReady, yet heard from
        (False, _node("Unknown"), ReleaseStep.FORCE),  # unreachable: never confirmed
        (True, _node("Unknown"), ReleaseStep.FORCE),  # the garbage collector was first
        (False, None, ReleaseStep.FORCE),  # no node left to confirm it
    ],
)
def test_release_step_decision_table(
    *, terminating: bool, node: dict[str, Any] | None, step: ReleaseStep
) -> None:
    pod = live_pod()
    pod["metadata"]["annotations"][LABEL_NODE] = "node-a"  # as component_pod makes it
    if terminating:
        pod["metadata"]["deletionTimestamp"] = "2026-05-01T12:00:00Z"
    assert release_step(pod, node) is step
    assert pod_node(pod) == "node-a"
