"""How kwok plays the pods of the sandbox: like its default, but Job pods may run a while.

kwok's built-in pod lifecycle completes a Job's pod the instant it is Running, so a
Mission's onboard workloads would finish seconds after they start and the sandbox's
failover would always hit a vehicle whose mission is already over. These Stage objects
(kwok's ``--config``) give pods the same three steps (ready, complete for Job pods,
delete) with one difference: a pod annotated ``roost.dev/sandbox-runtime: 10m`` stays
Running that long before kwok completes it. Without the annotation a Job pod completes at
once, as before. Node stages are left to kwok's defaults (it keeps them for any kind the
file has no stages for).

The status templates are Go templates rendered by kwok (``Now``, ``Quote``,
``NodeIPWith``, ``PodIPWith`` are its functions); they fill in what the controllers read:
phase, conditions, container states, pod and host IPs.
"""

from __future__ import annotations

from typing import Any

from roost_api.wellknown import PREFIX
from roost_localcluster.kwoknodes import stage

RUNTIME_ANNOTATION = f"{PREFIX}sandbox-runtime"
"""Pod annotation: how long kwok keeps a Job's pod Running (a Go duration, e.g. ``10m``)."""

_POD = {"apiGroup": "v1", "kind": "Pod"}
_NOT_DELETING = {"key": ".metadata.deletionTimestamp", "operator": "DoesNotExist"}

_RUNNING_STATUS = """\
{{ $now := Now }}
phase: Running
startTime: {{ $now | Quote }}
hostIP: {{ NodeIPWith .spec.nodeName | Quote }}
podIP: {{ PodIPWith .spec.nodeName ( or .spec.hostNetwork false ) ( or .metadata.uid "" ) \
( or .metadata.name "" ) ( or .metadata.namespace "" ) | Quote }}
conditions:
- {type: Initialized, status: "True", lastTransitionTime: {{ $now | Quote }}}
- {type: ContainersReady, status: "True", lastTransitionTime: {{ $now | Quote }}}
- {type: Ready, status: "True", lastTransitionTime: {{ $now | Quote }}}
initContainerStatuses:
{{ range .spec.initContainers }}
- name: {{ .name | Quote }}
  image: {{ .image | Quote }}
  ready: true
  restartCount: 0
  state: {terminated: {exitCode: 0, reason: Completed, startedAt: {{ $now | Quote }}, \
finishedAt: {{ $now | Quote }}}}
{{ end }}
containerStatuses:
{{ range .spec.containers }}
- name: {{ .name | Quote }}
  image: {{ .image | Quote }}
  ready: true
  started: true
  restartCount: 0
  state: {running: {startedAt: {{ $now | Quote }}}}
{{ end }}
"""

_SUCCEEDED_STATUS = """\
{{ $now := Now }}
phase: Succeeded
conditions:
- {type: Ready, status: "False", reason: PodCompleted, lastTransitionTime: {{ $now | Quote }}}
- {type: ContainersReady, status: "False", reason: PodCompleted, \
lastTransitionTime: {{ $now | Quote }}}
containerStatuses:
{{ range .spec.containers }}
- name: {{ .name | Quote }}
  image: {{ .image | Quote }}
  ready: false
  started: false
  restartCount: 0
  state: {terminated: {exitCode: 0, reason: Completed, startedAt: {{ $now | Quote }}, \
finishedAt: {{ $now | Quote }}}}
{{ end }}
"""


def pod_stages() -> list[dict[str, Any]]:
    """The three pod Stages described in the module docstring."""
    return [
        stage(
            "roost-pod-ready",
            _POD,
            {
                "selector": {
                    "matchExpressions": [
                        _NOT_DELETING,
                        {"key": ".status.podIP", "operator": "DoesNotExist"},
                    ]
                },
                "next": {"statusTemplate": _RUNNING_STATUS},
            },
        ),
        stage(
            "roost-pod-complete",
            _POD,
            {
                "selector": {
                    "matchExpressions": [
                        _NOT_DELETING,
                        {"key": ".status.phase", "operator": "In", "values": ["Running"]},
                        {
                            "key": ".metadata.ownerReferences.[].kind",
                            "operator": "In",
                            "values": ["Job"],
                        },
                    ]
                },
                "delay": {
                    "durationMilliseconds": 0,
                    "durationFrom": {
                        "expressionFrom": f'.metadata.annotations["{RUNTIME_ANNOTATION}"]'
                    },
                },
                "next": {"statusTemplate": _SUCCEEDED_STATUS},
            },
        ),
        stage(
            "roost-pod-delete",
            _POD,
            {
                "selector": {
                    "matchExpressions": [
                        {"key": ".metadata.deletionTimestamp", "operator": "Exists"}
                    ]
                },
                "next": {"finalizers": {"empty": True}, "delete": True},
            },
        ),
    ]
