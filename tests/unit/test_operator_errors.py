"""Temporary vs permanent API errors (roost_operator.errors) and their kopf mapping
(roost_operator.edge)."""

from __future__ import annotations

import kopf
import pytest
from urllib3.exceptions import ReadTimeoutError

from roost_operator.edge import at_the_edge
from roost_operator.errors import describe, is_temporary
from roost_operator.kube import ApiError, ConflictError

REFUSED = '{"kind":"Status","message":"Job.batch \\"x\\" is invalid: name too long"}'


@pytest.mark.parametrize(
    ("status", "temporary"),
    [
        (400, False),
        (403, False),
        (404, False),
        (408, True),
        (409, True),
        (422, False),
        (429, True),
        (500, True),
        (503, True),
        (504, True),
    ],
)
def test_http_statuses_are_sorted_into_temporary_and_permanent(
    status: int, *, temporary: bool
) -> None:
    assert is_temporary(ApiError(status, "POST", "/x", "{}")) is temporary


def test_transport_failures_are_temporary_and_other_exceptions_are_not() -> None:
    assert is_temporary(ReadTimeoutError(None, "/x", "read timed out"))  # type: ignore[arg-type]
    assert is_temporary(ConnectionResetError())
    assert is_temporary(TimeoutError())
    assert not is_temporary(ValueError("a bug"))


def test_objects_are_named_with_their_kind_and_namespace() -> None:
    assert describe("Vehicle", "drone-1") == "Vehicle drone-1"
    assert describe("Mission", "survey", "flights") == "Mission flights/survey"


def test_a_temporary_error_becomes_kopfs_temporary_error_with_the_delay() -> None:
    with pytest.raises(kopf.TemporaryError) as caught, at_the_edge("Vehicle", "drone-1", 3.0):
        raise ConflictError(409, "PATCH", "/v", "{}")
    assert caught.value.delay == 3.0
    assert str(caught.value).startswith("Vehicle drone-1: ")


def test_a_permanent_error_becomes_kopfs_permanent_error_naming_the_object() -> None:
    edge = at_the_edge("Mission", "survey", 3.0, namespace="flights")
    with pytest.raises(kopf.PermanentError) as caught, edge:
        raise ApiError(422, "POST", "/jobs", REFUSED)
    assert str(caught.value).startswith("Mission flights/survey: ")
    assert "name too long" in str(caught.value)


def test_other_exceptions_pass_through_unchanged() -> None:
    with pytest.raises(KeyError), at_the_edge("Vehicle", "drone-1", 1.0):
        raise KeyError("bug")
