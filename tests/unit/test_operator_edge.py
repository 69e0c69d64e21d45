"""roost_operator.edge: API errors leave a kopf handler as kopf's temporary or permanent
errors, naming the object."""

from __future__ import annotations

from typing import Any

import kopf
import pytest

from roost_kube.errors import ApiUnavailableError, error_for_status
from roost_operator.edge import (
    CONFLICT_DELAY_S,
    UNAVAILABLE_DELAY_S,
    at_the_edge,
    describe,
    handler_edge,
    kopf_error,
    object_name,
)
from tests.support.kopfstub import Resource


@pytest.mark.parametrize(
    ("status", "kopf_class", "delay"),
    [
        (409, kopf.TemporaryError, CONFLICT_DELAY_S),
        (429, kopf.TemporaryError, UNAVAILABLE_DELAY_S),
        (500, kopf.TemporaryError, UNAVAILABLE_DELAY_S),
        (503, kopf.TemporaryError, UNAVAILABLE_DELAY_S),
        (400, kopf.PermanentError, None),
        (403, kopf.PermanentError, None),
        (404, kopf.PermanentError, None),
        (422, kopf.PermanentError, None),
    ],
)
def test_the_kopf_decision_table(status: int, kopf_class: type, delay: float | None) -> None:
    mapped = kopf_error(error_for_status(status, "PATCH", "/x", "{}"), "Vehicle v1")
    assert type(mapped) is kopf_class
    if delay is not None:
        assert isinstance(mapped, kopf.TemporaryError) and mapped.delay == delay
    assert str(mapped).startswith("Vehicle v1: PATCH /x")


def test_no_answer_at_all_is_temporary() -> None:
    error = ApiUnavailableError(None, "GET", "/x", "refused", transport="refused")
    mapped = kopf_error(error, "Vehicle v1")
    assert isinstance(mapped, kopf.TemporaryError) and mapped.delay == UNAVAILABLE_DELAY_S


def test_the_object_is_named_with_kind_and_namespace() -> None:
    assert (
        object_name({"resource": Resource(kind="Mission"), "name": "m", "namespace": "ns"})
        == "Mission ns/m"
    )
    assert object_name({"name": "v"}) == "object v"


def test_other_exceptions_pass_through_untouched() -> None:
    @handler_edge
    def buggy(**_: Any) -> None:
        raise KeyError("bug")

    with pytest.raises(KeyError):
        buggy()


def test_work_on_another_object_is_named_after_that_object() -> None:
    """A Node event reconciling a Vehicle: the message names the Vehicle."""
    with pytest.raises(kopf.PermanentError) as caught, at_the_edge("Vehicle", "drone-1"):
        raise error_for_status(422, "PATCH", "/deployments/x", '{"message":"too long"}')
    assert str(caught.value).startswith("Vehicle drone-1: ")
    edge = at_the_edge("Mission", "survey", namespace="flights")
    with pytest.raises(kopf.TemporaryError) as temporary, edge:
        raise error_for_status(409, "PATCH", "/x", "{}")
    assert str(temporary.value).startswith("Mission flights/survey: ")
    assert describe("Mission", "survey", "flights") == "Mission flights/survey"


def test_other_exceptions_pass_the_edge_unchanged() -> None:
    with pytest.raises(KeyError), at_the_edge("Vehicle", "drone-1"):
        raise KeyError("a bug")
