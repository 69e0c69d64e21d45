"""Copying a final Mission bundle to an S3-compatible bucket, when one is configured.

The records volume is the bundle's first home (``roost records get`` and the dashboard
read it there); the bucket is the long-term one, off the ground station. Once gathering
has made the bundle final (Complete or Partial), the Mission's reconcile loop runs an
upload round per reconcile until ``status.records.upload`` is final, like gathering:
the loop stays the only writer of the Mission's status.

A round puts every file the manifest lists, then ``manifest.json`` last — so a manifest in
the bucket means the whole bundle is there. An object already in the bucket with the
same SHA-256 (its ``sha256`` metadata, read by HEAD) is skipped: a round cut by a network
fault or an operator restart resumes with what is missing, and a finished bundle is
never uploaded twice.

What a failure does (:func:`after_attempt`, decision table in
``tests/unit/test_operator_records_upload.py``):

* the bucket refuses (bad credentials, no such bucket, wrong region, access denied, the
  Secret missing): ``Failed`` with the bucket's answer, once, and not tried again;
* temporary (unreachable, timeout, 5xx, throttling): ``Pending``, tried again after
  ``retry_seconds`` doubling per failure up to :data:`MAX_BACKOFF`, and ``Failed`` once the
  bundle has waited ``give_up_after`` since it became final — never retried forever.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import urllib3

from roost_api.mission import MissionRecordsStatus, RecordsState, RecordsUploadStatus, UploadState
from roost_api.records import sha256_of
from roost_operator.records.bundle import MANIFEST, Bundle
from roost_operator.records.planning import safe_path
from roost_operator.records.s3 import BucketError, BucketSettings, Client, Credentials
from roost_operator.records.settings import RecordsSettings

log = logging.getLogger(__name__)
POOL = urllib3.PoolManager(maxsize=4)
MAX_BACKOFF = timedelta(minutes=15)


@dataclass(frozen=True)
class Attempt:
    """What one upload round did."""

    objects: int = 0
    """Objects now in the bucket (put or found there with the same SHA-256)."""
    put: int = 0
    bytes_put: int = 0
    error: BucketError | None = None


def start_upload(
    records: MissionRecordsStatus, bucket: BucketSettings
) -> RecordsUploadStatus | None:
    """The first ``upload`` of a bundle that just became final; None when there is
    nothing to upload (no bucket configured: the caller passes none; no bundle written)."""
    if RecordsState(records.state) in (RecordsState.GATHERING, RecordsState.FAILED):
        return None
    return RecordsUploadStatus(
        state=UploadState.PENDING,
        location=bucket.location(records.bundle) + "/",
        message="uploading",
    )


def due(upload: RecordsUploadStatus | None, now: datetime) -> bool:
    """An upload round is to run now."""
    if upload is None or UploadState(upload.state).final:
        return False
    return upload.next_attempt_time is None or upload.next_attempt_time <= now


def backoff(attempts: int, retry_seconds: float) -> timedelta:
    """The wait after the ``attempts``-th temporary failure in a row."""
    seconds = retry_seconds * 2 ** max(attempts - 1, 0)
    return min(timedelta(seconds=seconds), MAX_BACKOFF)


def after_attempt(
    upload: RecordsUploadStatus,
    attempt: Attempt,
    *,
    ready_time: datetime | None,
    now: datetime,
    settings: RecordsSettings,
) -> RecordsUploadStatus:
    """The ``upload`` status after a round (pure)."""
    if attempt.error is None:
        return upload.model_copy(
            update={
                "state": UploadState.COMPLETE,
                "message": None,
                "objects": attempt.objects,
                "next_attempt_time": None,
                "complete_time": now,
            }
        )
    objects = max(upload.objects, attempt.objects)
    if attempt.error.permanent:
        return upload.model_copy(
            update={
                "state": UploadState.FAILED,
                "message": f"the bucket refused the bundle: {attempt.error}",
                "objects": objects,
                "next_attempt_time": None,
            }
        )
    attempts = upload.attempts + 1
    if ready_time is not None and now - ready_time >= settings.give_up_after:
        return upload.model_copy(
            update={
                "state": UploadState.FAILED,
                "message": (
                    f"gave up after {attempts} tries over "
                    f"{settings.give_up_after.total_seconds() / 3600:g} h: {attempt.error}"
                ),
                "objects": objects,
                "attempts": attempts,
                "next_attempt_time": None,
            }
        )
    wait = backoff(attempts, settings.retry_seconds)
    return upload.model_copy(
        update={
            "state": UploadState.PENDING,
            "message": (
                f"try {attempts} failed, trying again in {wait.total_seconds():g} s: "
                f"{attempt.error}"
            ),
            "objects": objects,
            "attempts": attempts,
            "next_attempt_time": now + wait,
        }
    )


def upload_bundle(root: Path, client: Client) -> Attempt:
    """Put the bundle's files that the bucket lacks, then its manifest (I/O)."""
    bundle = Bundle(root)
    manifest = bundle.manifest()
    if not manifest:
        return Attempt(
            error=BucketError(
                f"the bundle is not on the records volume ({root}: no manifest)", permanent=True
            )
        )
    files = [(str(f["path"]), str(f["sha256"])) for f in manifest.get("files", [])]
    files.append((MANIFEST, ""))
    objects = put = sent = 0
    try:
        for relative, listed in files:
            if not safe_path(relative):
                raise BucketError(f"refused path {relative!r} in the manifest", permanent=True)
            path = root / relative
            try:
                digest = listed or sha256_of(path)
            except OSError as error:
                raise BucketError(f"{relative}: {error.strerror}", permanent=True) from error
            key = client.settings.key(root.name, relative)
            if client.stored_sha256(key) != digest:
                kind = (
                    "application/json" if relative.endswith(".json") else "application/octet-stream"
                )
                try:
                    client.put_file(key, path, digest, kind)
                except FileNotFoundError as error:
                    raise BucketError(
                        f"{relative}: not on the records volume", permanent=True
                    ) from error
                put += 1
                sent += path.stat().st_size
            objects += 1
    except BucketError as error:
        return Attempt(objects, put, sent, error)
    return Attempt(objects, put, sent)


def upload_round(
    records: MissionRecordsStatus, settings: RecordsSettings, now: datetime
) -> MissionRecordsStatus:
    """One upload round for a final bundle; returns ``status.records`` with its new
    ``upload`` (unchanged when no round is due)."""
    bucket = settings.bucket
    assert bucket is not None and settings.directory is not None
    upload = records.upload or start_upload(records, bucket)
    if upload is None or not due(upload, now):
        return records.model_copy(update={"upload": upload})
    try:
        client = Client(bucket, Credentials.from_directory(bucket.credentials_dir), POOL)
        attempt = upload_bundle(settings.directory / records.bundle, client)
    except BucketError as error:
        attempt = Attempt(error=error)
    updated = after_attempt(
        upload, attempt, ready_time=records.ready_time, now=now, settings=settings
    )
    if updated.state != upload.state or updated.attempts != upload.attempts:
        level = logging.INFO if updated.state == UploadState.COMPLETE else logging.WARNING
        log.log(
            level,
            "records: bundle %s to %s: %s (%d objects, %d put, %d bytes)%s",
            records.bundle,
            upload.location,
            updated.state,
            attempt.objects,
            attempt.put,
            attempt.bytes_put,
            f": {updated.message}" if updated.message else "",
        )
    return records.model_copy(update={"upload": updated})
