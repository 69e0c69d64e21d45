"""The records settings: where bundles live, how long gathering waits, what retention keeps.

Separate from :mod:`roost_operator.settings` only so the pure planning can take it
without importing the operator's other settings.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

from roost_operator.records.s3 import BucketSettings


@dataclass(frozen=True)
class RecordsSettings:
    """How the operator gathers and keeps Mission records (``ROOST_RECORDS_*``)."""

    directory: Path | None = None
    """Where bundles are written (``ROOST_RECORDS_DIR``; the chart mounts its
    PersistentVolumeClaim there). None: records are not gathered."""

    agent_port: int = 9468
    """The agents' records port (``ROOST_RECORDS_AGENT_PORT``), reached through the API
    server's pod proxy of the agent pod on the vehicle's node."""

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
