"""The copy of a Mission bundle in an S3-compatible bucket, the pure part: what a round's
outcome does to ``status.records.upload`` (decision table), the backoff, when a round is
due, and the request signature (AWS Signature Version 4) against the example AWS
publishes for it. The uploads themselves are tested against a real S3-compatible server
in ``tests/integration/test_records_s3.py``. No mocks.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from roost_api.mission import (
    MissionRecordsStatus,
    RecordsState,
    RecordsUploadStatus,
    UploadState,
)
from roost_operator.records.s3 import (
    EMPTY_SHA256,
    BucketError,
    BucketSettings,
    Credentials,
    error_of,
    sign,
)
from roost_operator.records.settings import RecordsSettings
from roost_operator.records.upload import (
    MAX_BACKOFF,
    Attempt,
    after_attempt,
    backoff,
    due,
    start_upload,
)

READY = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)
SETTINGS = RecordsSettings(retry_seconds=30, give_up_after=timedelta(hours=24))
BUCKET = BucketSettings("http://127.0.0.1:9000", "flights", prefix="/roost/")
PENDING = RecordsUploadStatus(state=UploadState.PENDING, location="s3://flights/roost/b/")
PERMANENT = BucketError("HTTP 403 (InvalidAccessKeyId: no such key)", permanent=True)
TEMPORARY = BucketError("unreachable (ConnectionRefusedError)", permanent=False)


def at(minutes: float) -> datetime:
    return READY + timedelta(minutes=minutes)


# (case, attempts before, the round's outcome, minutes after ready) ->
#   (state, attempts after, next try in seconds (None: none), message contains)
TABLE = [
    ("all there", 0, Attempt(objects=5, put=5), 0, ("Complete", 0, None, "")),
    ("all there after failures", 3, Attempt(objects=5, put=2), 10, ("Complete", 3, None, "")),
    ("credentials refused", 0, Attempt(error=PERMANENT), 0,
     ("Failed", 0, None, "refused the bundle: HTTP 403 (InvalidAccessKeyId")),
    ("refused after temporary ones", 4, Attempt(objects=2, error=PERMANENT), 30,
     ("Failed", 4, None, "InvalidAccessKeyId")),
    ("first network failure", 0, Attempt(error=TEMPORARY), 0,
     ("Pending", 1, 30, "try 1 failed, trying again in 30 s: unreachable")),
    ("third network failure doubles", 2, Attempt(objects=3, error=TEMPORARY), 5,
     ("Pending", 3, 120, "try 3 failed")),
    ("backoff capped", 20, Attempt(error=TEMPORARY), 60,
     ("Pending", 21, MAX_BACKOFF.total_seconds(), "try 21")),
    ("unreachable a day: given up", 40, Attempt(error=TEMPORARY), 24 * 60,
     ("Failed", 41, None, "gave up after 41 tries over 24 h: unreachable")),
]  # fmt: skip


@pytest.mark.parametrize(
    ("before", "attempt", "minutes", "expected"),
    [case[1:] for case in TABLE],
    ids=[case[0] for case in TABLE],
)
def test_a_rounds_outcome_decides_the_upload_status(
    before: int, attempt: Attempt, minutes: float, expected: tuple[str, int, float | None, str]
) -> None:
    state, attempts, next_in, says = expected
    upload = PENDING.model_copy(update={"attempts": before})
    now = at(minutes)
    after = after_attempt(upload, attempt, ready_time=READY, now=now, settings=SETTINGS)
    assert (after.state, after.attempts) == (state, attempts)
    if next_in is None:
        assert after.next_attempt_time is None
    else:
        assert after.next_attempt_time == now + timedelta(seconds=next_in)
    assert says in (after.message or "")
    assert UploadState(after.state).final == (state != "Pending")
    if state == "Complete":
        assert after.complete_time == now and after.objects == attempt.objects


def test_objects_already_counted_are_not_forgotten_by_a_failed_round() -> None:
    upload = PENDING.model_copy(update={"objects": 7})
    after = after_attempt(
        upload, Attempt(objects=2, error=TEMPORARY), ready_time=READY, now=at(1), settings=SETTINGS
    )
    assert after.objects == 7


def test_backoff_doubles_from_the_retry_interval_up_to_the_cap() -> None:
    assert [backoff(n, 30).total_seconds() for n in (1, 2, 3, 4, 5, 6, 7)] == [
        30, 60, 120, 240, 480, 900, 900
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("upload", "now", "expected"),
    [
        (None, at(0), False),
        (PENDING, at(0), True),
        (PENDING.model_copy(update={"next_attempt_time": at(5)}), at(4), False),
        (PENDING.model_copy(update={"next_attempt_time": at(5)}), at(5), True),
        (PENDING.model_copy(update={"state": UploadState.COMPLETE}), at(0), False),
        (PENDING.model_copy(update={"state": UploadState.FAILED}), at(0), False),
    ],
    ids=["none", "new", "waiting", "time", "complete", "failed"],
)
def test_a_round_is_due_only_for_a_pending_upload_whose_time_has_come(
    upload: RecordsUploadStatus | None, now: datetime, expected: bool
) -> None:
    assert due(upload, now) is expected


@pytest.mark.parametrize(
    ("state", "starts"),
    [
        (RecordsState.GATHERING, False),
        (RecordsState.COMPLETE, True),
        (RecordsState.PARTIAL, True),
        (RecordsState.FAILED, False),
    ],
)
def test_only_a_final_written_bundle_is_uploaded(state: RecordsState, starts: bool) -> None:
    records = MissionRecordsStatus(state=state, bundle="flights_m_0123abcd")
    upload = start_upload(records, BUCKET)
    assert (upload is not None) is starts
    if upload is not None:
        assert upload.state == UploadState.PENDING
        assert upload.location == "s3://flights/roost/flights_m_0123abcd/"


def test_keys_join_the_prefix_without_doubled_slashes() -> None:
    assert BUCKET.key("b", "vehicles/a/f/hub.tlog") == "roost/b/vehicles/a/f/hub.tlog"
    assert BucketSettings("http://h", "x").key("b", "manifest.json") == "b/manifest.json"


def test_the_signature_is_the_one_aws_publishes_for_its_get_object_example() -> None:
    """The "GET Object" example of AWS's Signature Version 4 documentation for S3
    (the documented example credentials, not real ones)."""
    credentials = Credentials("AKIAIOSFODNN7EXAMPLE", "wJalrXUtnFEMI/K7MDENG/bPxRfiCYEXAMPLEKEY")
    signed = sign(
        "GET",
        "https://examplebucket.s3.amazonaws.com/test.txt",
        {"Range": "bytes=0-9"},
        EMPTY_SHA256,
        credentials=credentials,
        region="us-east-1",
        when=datetime(2013, 5, 24, tzinfo=UTC),
    )
    assert signed["authorization"] == (
        "AWS4-HMAC-SHA256 Credential=AKIAIOSFODNN7EXAMPLE/20130524/us-east-1/s3/aws4_request, "
        "SignedHeaders=host;range;x-amz-content-sha256;x-amz-date, "
        "Signature=f0e8bdb87c964420e857bd35b5d6ed310bd44f0170aba48dd91039c6036bdb41"
    )
    assert signed["x-amz-date"] == "20130524T000000Z"


def test_an_s3_error_document_gives_its_code_and_message() -> None:
    body = (
        b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>NoSuchBucket</Code>'
        b"<Message>The specified bucket does not exist</Message></Error>"
    )
    assert error_of(body) == ("NoSuchBucket", "The specified bucket does not exist")
    assert error_of(b"") == ("", "")
