"""kwok's Nodes reporting status like kubelets with node leases: rarely.

A kubelet renews its node Lease every quarter of the lease's duration (the heartbeat the
node lifecycle controller watches) and writes the Node's status only when something in
it changed or, failing that, every ``nodeStatusReportFrequency`` (five minutes by
default). kwok's built-in node heartbeat instead rewrites every node's status every
20 to 45 s, on top of the Lease renewals. With a thousand nodes that is dozens of writes a
second: on a two-core machine the API server spent more than half a core on them while
nothing else happened, which measures kwok rather than the fleet.

:func:`node_stages` are kwok Stage objects (its ``--config``) for Nodes that do what a
kubelet does: one stage makes a new node Ready (conditions, addresses, the kubelet
endpoint, ``phase: Running``), a second refreshes the conditions' heartbeat times every
``report_every_s`` seconds (with up to a tenth more of jitter, so a fleet created at once
does not report at once). The Lease renewals are kwok's own, as before. kwok keeps its
defaults for every other kind (pods).

The status templates are Go templates rendered by kwok: ``Now``, ``Quote``,
``NodeConditions`` (the usual Ready/pressure conditions), ``NodeIP`` and ``NodePort`` are
its functions.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final

KUBELET_REPORT_S: Final = 300
"""A kubelet's default ``nodeStatusReportFrequency``."""

_NODE = {"apiGroup": "v1", "kind": "Node"}
_READY = '.status.conditions.[] | select( .type == "Ready" ) | .status'

_CONDITIONS = """\
{{ $now := Now }}
{{ $since := or .metadata.creationTimestamp $now }}
conditions:
{{ range NodeConditions }}
- type: {{ .type | Quote }}
  status: {{ .status | Quote }}
  reason: {{ .reason | Quote }}
  message: {{ .message | Quote }}
  lastHeartbeatTime: {{ $now | Quote }}
  lastTransitionTime: {{ $since | Quote }}
{{ end }}
"""

_READY_STATUS = (
    _CONDITIONS
    + """\
addresses:
{{ with NodeIP }}
- {type: InternalIP, address: {{ . | Quote }}}
{{ end }}
- {type: Hostname, address: {{ .metadata.name | Quote }}}
{{ with NodePort }}
daemonEndpoints:
  kubeletEndpoint:
    Port: {{ . }}
{{ end }}
phase: Running
"""
)


def stage(name: str, resource: Mapping[str, str], spec: Mapping[str, Any]) -> dict[str, Any]:
    """A kwok Stage object named ``name`` for objects of ``resource`` (``apiGroup``,
    ``kind``) with the rest of its ``spec`` (selector, delay, next)."""
    return {
        "apiVersion": "kwok.x-k8s.io/v1alpha1",
        "kind": "Stage",
        "metadata": {"name": name},
        "spec": {"resourceRef": dict(resource), **spec},
    }


def node_stages(report_every_s: float = KUBELET_REPORT_S) -> list[dict[str, Any]]:
    """The two Node Stages described in the module docstring."""
    period_ms = round(report_every_s * 1000)
    return [
        stage(
            "roost-node-ready",
            _NODE,
            {
                "selector": {
                    "matchExpressions": [{"key": _READY, "operator": "NotIn", "values": ["True"]}]
                },
                "next": {"statusTemplate": _READY_STATUS},
            },
        ),
        stage(
            "roost-node-report",
            _NODE,
            {
                "selector": {
                    "matchExpressions": [
                        {"key": ".status.phase", "operator": "In", "values": ["Running"]},
                        {"key": _READY, "operator": "In", "values": ["True"]},
                    ]
                },
                "delay": {
                    "durationMilliseconds": period_ms,
                    "jitterDurationMilliseconds": period_ms + period_ms // 10,
                },
                "next": {"statusTemplate": _CONDITIONS},
            },
        ),
    ]
