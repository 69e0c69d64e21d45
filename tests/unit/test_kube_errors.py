"""roost_kube.errors: the temporary/permanent decision table.

Transport failures told apart on real sockets (a refused port, a listener that never
answers) are in ``tests/integration/test_kube_errors_sockets.py``.
"""

from __future__ import annotations

import json

import pytest
from kubernetes.client.exceptions import ApiException

from roost_kube.errors import (
    ApiError,
    ApiUnavailableError,
    ConflictError,
    ForbiddenError,
    InvalidError,
    NotFoundError,
    PermanentApiError,
    error_class,
    error_for_status,
    from_client_exception,
    transport_of,
)


@pytest.mark.parametrize(
    ("status", "cls", "temporary"),
    [
        (409, ConflictError, True),
        (408, ApiUnavailableError, True),
        (429, ApiUnavailableError, True),
        (500, ApiUnavailableError, True),
        (503, ApiUnavailableError, True),
        (504, ApiUnavailableError, True),
        (400, InvalidError, False),
        (422, InvalidError, False),
        (401, ForbiddenError, False),
        (403, ForbiddenError, False),
        (404, NotFoundError, False),
        (405, PermanentApiError, False),
        (413, PermanentApiError, False),
    ],
)
def test_the_decision_table(status: int, cls: type[ApiError], temporary: bool) -> None:
    assert error_class(status) is cls
    error = error_for_status(status, "PATCH", "/x", "{}")
    assert type(error) is cls and error.temporary is temporary


def test_the_server_message_and_reason_are_kept() -> None:
    body = json.dumps({"kind": "Status", "message": "name too long", "reason": "Invalid"})
    error = error_for_status(422, "POST", "/apis/apps/v1/namespaces/n/deployments", body)
    assert (error.message, error.reason, error.status) == ("name too long", "Invalid", 422)
    assert str(error) == "POST /apis/apps/v1/namespaces/n/deployments: HTTP 422: name too long"
    exists = error_for_status(409, "POST", "/x", json.dumps({"reason": "AlreadyExists"}))
    assert isinstance(exists, ConflictError) and exists.already_exists


def test_a_body_that_is_not_json_is_its_own_message() -> None:
    error = error_for_status(502, "GET", "/x", "<html>bad gateway</html>")
    assert error.message == "<html>bad gateway</html>" and error.reason == ""


def test_client_api_exceptions_map_by_status_and_bugs_are_not_swallowed() -> None:
    answer = ApiException(status=403, reason="Forbidden")
    answer.body = json.dumps({"message": "no"})
    mapped = from_client_exception(answer, "GET", "/x")
    assert isinstance(mapped, ForbiddenError) and mapped.message == "no"
    assert from_client_exception(KeyError("bug"), "GET", "/x") is None
    assert transport_of(ValueError("bug")) is None
