"""The API's single source of truth: generated CRDs are current, examples are valid.

Offline checks only; tests/integration/test_control_plane.py sends the same examples to a
real API server, where the CEL rules run too.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from roost_api import crd
from roost_api.meta import Condition, set_condition
from roost_api.resources import KINDS

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("*.yaml"))
INVALID = sorted((ROOT / "examples" / "invalid").glob("*.yaml"))
BY_KIND = {kind.kind: kind for kind in KINDS}


def _documents(path: Path) -> list[dict[str, Any]]:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc]


def _crd_schema(kind: str) -> dict[str, Any]:
    text = (ROOT / "crds" / crd.file_name(BY_KIND[kind])).read_text()
    schema: dict[str, Any] = yaml.safe_load(text)["spec"]["versions"][0]["schema"][
        "openAPIV3Schema"
    ]
    return schema


def test_committed_crds_match_what_the_models_generate() -> None:
    for name, text in crd.generate_all().items():
        committed = ROOT / "crds" / name
        assert committed.exists(), f"{name} missing: run `make crds`"
        assert committed.read_text() == text, f"{name} is out of date: run `make crds`"


def test_every_crd_is_structural_with_status_columns_and_category() -> None:
    for kind in KINDS:
        body = crd.build_crd(kind)
        version = body["spec"]["versions"][0]
        assert version["subresources"] == {"status": {}}
        assert body["spec"]["names"]["categories"] == ["roost"]
        assert body["spec"]["names"]["shortNames"]
        assert len(version["additionalPrinterColumns"]) >= 4

        def walk(node: dict[str, Any], path: str) -> None:
            assert "$ref" not in node and "anyOf" not in node, path
            untyped_ok = node.get("x-kubernetes-int-or-string") or node.get(
                "x-kubernetes-preserve-unknown-fields"
            )
            assert "type" in node or untyped_ok, f"untyped node at {path}"
            for key, child in node.get("properties", {}).items():
                walk(child, f"{path}.{key}")
            if isinstance(node.get("items"), dict):
                walk(node["items"], f"{path}[]")
            if isinstance(node.get("additionalProperties"), dict):
                walk(node["additionalProperties"], f"{path}{{}}")

        walk(version["schema"]["openAPIV3Schema"], kind.kind)


def test_every_field_of_the_models_is_documented() -> None:
    for kind in KINDS:
        spec = crd.build_crd(kind)["spec"]["versions"][0]["schema"]["openAPIV3Schema"]

        def walk(node: dict[str, Any], path: str, embedded: bool) -> None:
            for key, child in node.get("properties", {}).items():
                inside = embedded or key in ("onboard", "offboard")
                if not embedded:
                    assert child.get("description"), f"{path}.{key} has no description"
                walk(child, f"{path}.{key}", inside)
            if isinstance(node.get("items"), dict):
                walk(node["items"], f"{path}[]", embedded)

        for part in ("spec", "status"):
            walk(spec["properties"][part], f"{kind.kind}.{part}", False)


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_valid_example_passes_the_generated_schema_and_the_models(path: Path) -> None:
    for doc in _documents(path):
        jsonschema.Draft4Validator(_crd_schema(doc["kind"])).validate(doc)
        BY_KIND[doc["kind"]].spec_model.model_validate(doc["spec"])


def test_examples_cover_a_real_and_two_simulated_vehicles_and_a_mission() -> None:
    docs = [doc for path in EXAMPLES for doc in _documents(path)]
    vehicles = [d for d in docs if d["kind"] == "Vehicle"]
    stacks = {d["spec"].get("simulation", {}).get("stack") for d in vehicles}
    assert stacks >= {None, "px4", "ardupilot"}
    assert {d["kind"] for d in docs} == {"Vehicle", "RedundantAutopilot", "Mission"}


def test_invalid_examples_say_what_error_a_user_sees() -> None:
    assert len(INVALID) >= 40
    for path in INVALID:
        first = path.read_text().splitlines()[0]
        assert first.startswith("# expect: "), f"{path.name} lacks its expected error"


def test_set_condition_moves_transition_time_only_when_status_changes() -> None:
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    later = t0 + timedelta(minutes=5)
    conds = set_condition([], type="Ready", status="False", reason="NodeMissing", at=t0)
    same = set_condition(conds, type="Ready", status="False", reason="NodeNotReady", at=later)
    assert same[0].last_transition_time == t0
    assert same[0].reason == "NodeNotReady"
    moved = set_condition(same, type="Ready", status="True", reason="AllReady", at=later)
    assert moved[0].last_transition_time == later
    assert [c.type for c in set_condition(moved, type="X", status="True", reason="Y")] == [
        "Ready",
        "X",
    ]


def test_conditions_round_trip_in_kubernetes_shape() -> None:
    cond = Condition(
        type="Ready",
        status="True",
        reason="AllReady",
        last_transition_time=datetime(2026, 1, 1, tzinfo=UTC),
        observed_generation=3,
    )
    wire = cond.to_api()
    assert wire == {
        "type": "Ready",
        "status": "True",
        "reason": "AllReady",
        "message": "",
        "observedGeneration": 3,
        "lastTransitionTime": "2026-01-01T00:00:00Z",
    }
    assert Condition.model_validate(wire) == cond
