"""The records settings: where bundles live, how long gathering waits, what retention keeps.

Separate from :mod:`roost_operator.settings` only so the pure planning can take it
without importing the operator's other settings.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from enum import StrEnum
from pathlib import Path

from roost_operator.records.s3 import BucketSettings


class AgentRecords(StrEnum):
    """Whether the agents record flights and whether the operator can reach their records
    servers (``ROOST_RECORDS_AGENTS``; the chart derives it from ``agent.records.enabled``
    and ``agent.records.bindNodeAddress``)."""

    REACHABLE = "reachable"
    """The agents serve their records where the operator reaches them: on the node's
    address (through the API server's pod proxy), or at a Vehicle's ``roost.dev/records``
    URL. The operator gathers them into Mission bundles."""
    ON_VEHICLE = "on-vehicle"
    """The agents record but serve on the vehicle's 127.0.0.1 only (the chart's default:
    the records server is unauthenticated). The operator does not try to reach them: a
    Mission's bundle is made at once without its flights, and each vehicle's entry says
    where they are instead."""
    OFF = "off"
    """The agents do not record flights: there is nothing to gather."""


def parse_agent_records(text: str) -> AgentRecords:
    """``ROOST_RECORDS_AGENTS``; ValueError naming the accepted values otherwise."""
    try:
        return AgentRecords(text.strip().lower())
    except ValueError:
        accepted = ", ".join(a.value for a in AgentRecords)
        raise ValueError(f"ROOST_RECORDS_AGENTS={text!r}: expected one of {accepted}") from None


@dataclass(frozen=True)
class RecordsSettings:
    """How the operator gathers and keeps Mission records (``ROOST_RECORDS_*``)."""

    directory: Path | None = None
    """Where bundles are written (``ROOST_RECORDS_DIR``; the chart mounts its
    PersistentVolumeClaim there). None: records are not gathered."""

    agent_port: int = 9468
    """The agents' records port (``ROOST_RECORDS_AGENT_PORT``), reached through the API
    server's pod proxy of the agent pod on the vehicle's node."""

    agents: AgentRecords = AgentRecords.REACHABLE
    """Whether the agents' records can be gathered (``ROOST_RECORDS_AGENTS``: reachable,
    on-vehicle or off; see :class:`AgentRecords`). Reachable when unset, as for an
    operator run beside its agents; the chart always sets it."""

    agent_namespace: str = ""
    """Namespace of the agent pods (``ROOST_RECORDS_AGENT_NAMESPACE``; empty: the
    operator's own, where the chart runs the agent DaemonSet)."""

    retry_seconds: float = 30.0
    """Look again this often while a vehicle is unreachable or still landing
    (``ROOST_RECORDS_RETRY_SECONDS``)."""

    settle_after: timedelta = timedelta(minutes=15)
    """How long after the Mission ended a flight may still be recording or fetching its
    autopilots' logs before the bundle takes what is there (``ROOST_RECORDS_SETTLE_SECONDS``)."""

    give_up_after: timedelta = timedelta(hours=24)
    """How long after the Mission ended an unreachable vehicle is waited for before the
    bundle is closed as Partial without it (``ROOST_RECORDS_GIVE_UP_SECONDS``)."""

    keep_count: int = 100
    """Final bundles kept at most, newest first (``ROOST_RECORDS_KEEP``; 0: no limit)."""

    keep_for: timedelta | None = timedelta(days=30)
    """Final bundles older than this go (``ROOST_RECORDS_KEEP_DAYS``; 0: no limit)."""

    fetch_attempts: int = 3
    """Downloads of one file whose sha256 does not match before it counts as corrupt."""

    bucket: BucketSettings | None = None
    """Copy each final bundle to this S3-compatible bucket (``ROOST_RECORDS_S3_*``;
    None: the bundles stay on the records volume only)."""
