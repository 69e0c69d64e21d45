"""``roost records`` decisions (roost_cli.records): which Missions are listed, and what
``get`` says for each state of a Mission's record. Pure: Mission bodies as the API
server returns them."""

from __future__ import annotations

from typing import Any

import pytest

from roost_cli.errors import CliError
from roost_cli.records import bundle_of, record_rows


def mission(name: str, **status: Any) -> dict[str, Any]:
    return {"metadata": {"name": name, "namespace": "flights"}, "status": status}


RECORD = {"state": "Complete", "bundle": "flights_a_1234abcd", "vehicles": []}
GATHERING = {**RECORD, "state": "Gathering", "message": "pending: b"}
FAILED = {**RECORD, "state": "Failed", "message": "disk full"}


@pytest.mark.parametrize(
    ("status", "says"),
    [
        ({"phase": "Aborted"}, "never flew (it ended Aborted before starting)"),
        ({"phase": "Succeeded", "startTime": "t"}, "has no record"),
        ({"phase": "Running", "startTime": "t"}, "is Running: its record is gathered once it ends"),
        ({"phase": "Succeeded", "startTime": "t", "records": GATHERING}, "still being gathered"),
        ({"phase": "Failed", "startTime": "t", "records": FAILED}, "could not be written: disk"),
    ],
)  # fmt: skip
def test_get_says_why_a_mission_has_no_bundle_to_fetch(status: dict[str, Any], says: str) -> None:
    with pytest.raises(CliError, match="flights/a") as raised:
        bundle_of(mission("a", **status))
    assert says in str(raised.value)


@pytest.mark.parametrize("state", ["Complete", "Partial"])
def test_a_final_record_names_its_bundle(state: str) -> None:
    body = mission("a", phase="Succeeded", startTime="t", records={**RECORD, "state": state})
    assert bundle_of(body) == "flights_a_1234abcd"


def test_the_list_shows_missions_with_a_record_newest_first() -> None:
    vehicles = [{"name": "x", "state": "Complete"}, {"name": "y", "state": "Pending"}]
    rows = record_rows(
        [
            mission("old", phase="Succeeded", completionTime="2026-01-01T00:00Z", records=RECORD),
            mission("grounded", phase="Aborted"),
            mission(
                "new",
                phase="Failed",
                completionTime="2026-02-01T00:00Z",
                records={**GATHERING, "vehicles": vehicles, "message": "pending: y"},
            ),
        ]
    )  # fmt: skip
    assert [(r.mission, r.records, r.vehicles, r.message) for r in rows] == [
        ("new", "Gathering", "1/2", "pending: y"),
        ("old", "Complete", "0/0", ""),
    ]


def test_the_list_shows_where_the_copy_in_the_bucket_stands() -> None:
    refused = {
        "state": "Failed",
        "location": "s3://flights/a/",
        "message": "the bucket refused the bundle: HTTP 403 (InvalidAccessKeyId: no such key)",
    }
    rows = record_rows(
        [
            mission("a", phase="Succeeded", completionTime="2026-01-01T00:00Z",
                    records={**RECORD, "upload": refused}),
            mission("b", phase="Succeeded", completionTime="2026-01-02T00:00Z", records=RECORD),
        ]
    )  # fmt: skip
    assert [(r.mission, r.upload) for r in rows] == [("b", ""), ("a", "Failed")]
    assert rows[1].message == f"upload: {refused['message']}"
