"""Copying Mission bundles to a bucket, against a real S3-compatible server.

The server is moto's standalone S3-compatible server on 127.0.0.1 with authentication
on (:mod:`tests.support.s3server`): an S3-compatible service, not AWS. The operator's
own client signs every request; boto3 reads the objects back independently. The WiFi
relay of the records tests (:mod:`tests.support.wifilink`) sits between them where the
network is to fail. The bundle is laid out on disk as gathering leaves it; the rounds
are the ones the Mission's reconcile loop runs (:func:`upload_round`), called here
directly with the clock moved past each backoff. About 10 s, most of it the server
starting. The same upload from a running operator is in
``tests/integration/test_records_operator.py``.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from roost_api.mission import MissionRecordsStatus, RecordsState, UploadState
from roost_operator.records.bundle import Bundle
from roost_operator.records.s3 import BucketSettings, Client, Credentials
from roost_operator.records.settings import RecordsSettings
from roost_operator.records.upload import POOL, upload_bundle, upload_round
from tests.support.s3server import REGION, S3Server, s3_server
from tests.support.wifilink import WifiLink

pytestmark = pytest.mark.slow

NAME = "flights_survey_0123abcd"
FILES = {
    "vehicles/a/a-20260501T120000Z/hub.tlog": os.urandom(700_000),
    "vehicles/a/a-20260501T120000Z/decisions.jsonl": b'{"event": "Failover"}\n',
    "vehicles/a/a-20260501T120000Z/autopilot-logs/fc1/7.ulg": os.urandom(200_000),
}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    with s3_server(tmp_path_factory.mktemp("s3") / "server.log") as started:
        yield started


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def make_bundle(directory: Path) -> Path:
    """A final bundle as gathering leaves it: files, then the manifest listing them."""
    bundle = Bundle(directory / NAME)
    files = []
    for path, data in FILES.items():
        (bundle.root / path).parent.mkdir(parents=True, exist_ok=True)
        (bundle.root / path).write_bytes(data)
        files.append({"path": path, "bytes": len(data), "sha256": sha256(data)})
    stored = bundle.write_document("mission.json", {"status": {"phase": "Succeeded"}})
    files.append({"path": stored.path, "bytes": stored.bytes, "sha256": stored.sha256})
    bundle.write_manifest({"bundle": NAME, "state": "Complete", "files": files})
    return bundle.root


def settings_for(
    server: S3Server, tmp_path: Path, endpoint: str | None = None, prefix: str = ""
) -> RecordsSettings:
    secret = server.write_credentials(tmp_path / "secret")
    bucket = BucketSettings(
        endpoint or server.endpoint, server.bucket, REGION, prefix, credentials_dir=secret
    )
    return RecordsSettings(directory=tmp_path, retry_seconds=30, bucket=bucket)


def final_records(now: datetime) -> MissionRecordsStatus:
    return MissionRecordsStatus(state=RecordsState.COMPLETE, bundle=NAME, ready_time=now)


def test_a_bundle_is_uploaded_whole_once_and_each_object_carries_its_sha256(
    server: S3Server, tmp_path: Path
) -> None:
    root = make_bundle(tmp_path)
    settings = settings_for(server, tmp_path, prefix="site 1:a/")  # encoded once, signed
    now = datetime.now(UTC)
    records = upload_round(final_records(now), settings, now)
    upload = records.upload
    assert upload is not None and upload.state == UploadState.COMPLETE, upload
    assert upload.location == f"s3://{server.bucket}/site 1:a/{NAME}/"
    assert upload.objects == len(FILES) + 2  # mission.json and the manifest

    objects = server.objects()
    for path, data in FILES.items():
        assert objects[f"site 1:a/{NAME}/{path}"] == data
    assert objects[f"site 1:a/{NAME}/manifest.json"] == (root / "manifest.json").read_bytes()
    head = server.client().head_object(
        Bucket=server.bucket, Key=f"site 1:a/{NAME}/{next(iter(FILES))}"
    )
    assert head["Metadata"]["sha256"] == sha256(next(iter(FILES.values())))

    # A second upload of the same bundle finds everything there: nothing is sent again.
    assert settings.bucket is not None
    client = Client(settings.bucket, server.credentials, POOL)
    again = upload_bundle(root, client)
    assert (again.error, again.objects, again.put) == (None, len(FILES) + 2, 0)


def test_an_upload_cut_by_the_network_resumes_with_what_is_missing(
    server: S3Server, tmp_path: Path
) -> None:
    root = make_bundle(tmp_path)
    link = WifiLink(int(server.endpoint.rsplit(":", 1)[1]))
    settings = settings_for(server, tmp_path, endpoint=link.url.rstrip("/"), prefix="cut")
    now = datetime.now(UTC)
    try:
        # Out of range when the bundle becomes final: temporary, tried again later.
        records = upload_round(final_records(now), settings, now)
        assert records.upload is not None
        pending = records.upload
        assert (pending.state, pending.attempts) == (UploadState.PENDING, 1)
        assert pending.next_attempt_time == now + timedelta(seconds=30)
        assert "try 1 failed, trying again in 30 s" in (pending.message or "")
        assert "unreachable" in (pending.message or "")
        assert upload_round(records, settings, now + timedelta(seconds=10)) == records  # not due

        # Back in range, but the link drops after a few requests: part of it is there.
        link.up()
        link.drop_connection(5)
        later = now + timedelta(seconds=30)
        records = upload_round(records, settings, later)
        assert records.upload is not None
        cut = records.upload
        assert (cut.state, cut.attempts) == (UploadState.PENDING, 2), cut
        assert cut.next_attempt_time == later + timedelta(seconds=60)
        assert link.cuts == 1
        there = {k for k in server.objects() if k.startswith(f"cut/{NAME}/")}
        assert f"cut/{NAME}/manifest.json" not in there  # the manifest goes last

        # The next round sends only what is missing and completes.
        assert settings.bucket is not None
        client = Client(settings.bucket, server.credentials, POOL)
        rest = upload_bundle(root, client)
        assert rest.error is None and rest.put == len(FILES) + 2 - len(there)
        records = upload_round(records, settings, later + timedelta(seconds=60))
    finally:
        link.down()
    assert records.upload is not None and records.upload.state == UploadState.COMPLETE
    objects = server.objects()
    for path, data in FILES.items():
        assert objects[f"cut/{NAME}/{path}"] == data


@pytest.mark.parametrize(
    ("credentials", "says"),
    [
        (Credentials("AKIANOSUCHKEY0000000", "x" * 40), "InvalidAccessKeyId"),
        (None, "SignatureDoesNotMatch"),  # the right key id with a wrong secret
    ],
    ids=["unknown-key", "wrong-secret"],
)
def test_refused_credentials_fail_the_upload_once_and_for_good(
    server: S3Server, tmp_path: Path, credentials: Credentials | None, says: str
) -> None:
    make_bundle(tmp_path)
    settings = settings_for(server, tmp_path, prefix="refused")
    wrong = credentials or replace(server.credentials, secret_access_key="y" * 40)
    assert settings.bucket is not None
    server.write_credentials(settings.bucket.credentials_dir, wrong)
    now = datetime.now(UTC)
    records = upload_round(final_records(now), settings, now)
    failed = records.upload
    assert failed is not None and failed.state == UploadState.FAILED, failed
    assert UploadState(failed.state).final and failed.next_attempt_time is None
    assert "the bucket refused the bundle" in (failed.message or "")
    assert says in (failed.message or "") and "HTTP 403" in (failed.message or "")
    # Final: later rounds do nothing, and nothing reached the bucket.
    assert upload_round(records, settings, now + timedelta(hours=1)) == records
    assert not [k for k in server.objects() if k.startswith("refused/")]


def test_a_missing_bucket_secret_or_bundle_fails_the_upload_with_why(
    server: S3Server, tmp_path: Path
) -> None:
    make_bundle(tmp_path)
    settings = settings_for(server, tmp_path)
    assert settings.bucket is not None
    now = datetime.now(UTC)
    no_bucket = replace(settings, bucket=replace(settings.bucket, bucket="no-such-bucket"))
    upload = upload_round(final_records(now), no_bucket, now).upload
    assert upload is not None and upload.state == UploadState.FAILED
    assert "NoSuchBucket" in (upload.message or "")
    no_secret = replace(
        settings, bucket=replace(settings.bucket, credentials_dir=tmp_path / "no-secret")
    )
    upload = upload_round(final_records(now), no_secret, now).upload
    assert upload is not None and upload.state == UploadState.FAILED
    assert "credentials cannot be read" in (upload.message or "")
    # A bundle retention removed before it went up (a bucket configured later).
    gone = final_records(now).model_copy(update={"bundle": "flights_gone_00000000"})
    upload = upload_round(gone, settings, now).upload
    assert upload is not None and upload.state == UploadState.FAILED
    assert "the bundle is not on the records volume" in (upload.message or "")
