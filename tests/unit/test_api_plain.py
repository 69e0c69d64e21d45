"""The node agent's plain API classes (and its state file's) against the pydantic models
they are generated from.

The agent runs without pydantic (:mod:`roost_api.plain_gen` says why), so these tests
hold the generated loaders to their source: they must accept and reject the same inputs
as the models, and ``to_api`` must give the same JSON. Inputs are drawn around every
field's rules: missing and null fields, wrong types, lax forms pydantic converts (numeric
strings, integral floats, ``"yes"``), values at and beyond each bound, enum values and
near misses, unknown fields. That the committed modules are what the generator renders
now is checked in ``tests/integration/test_api_plain_gen.py`` (it runs ruff).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

from roost_agent import state_model, state_plain
from roost_agent.state import PersistedState
from roost_api import autopilot, meta, plain
from roost_api.autopilot_enums import FinalAction
from roost_api.plain_check import PlainValidationError
from roost_api.plain_gen import MODELS
from tests.support.specdoc import SPEC

STATUS = {
    "conditions": [
        {
            "type": "Ready",
            "status": "True",
            "reason": "Ready",
            "lastTransitionTime": "2026-05-01T12:00:00Z",
        }
    ],
    "activeAutopilot": "fc1",
    "autopilots": [{"name": "fc1", "level": "OK", "landedState": "InAir", "armed": True}],
    "lastFailover": {
        "time": "2026-05-01T12:00:01+00:00",
        "from": "fc1",
        "to": "fc2",
        "reason": "heartbeat lost",
        "latencyMs": 3,
        "trigger": "Automatic",
        "safetyRoutine": "Holding",
    },
    "lastCommand": {"id": "c-1", "result": "Executed", "time": 1777636800},
    "failoverCount": 1,
}


def _outcome(model: type[BaseModel], doc: object) -> tuple[str, Any]:
    try:
        return "ok", model.model_validate(doc).model_dump(
            by_alias=True, exclude_none=True, mode="json"
        )
    except ValidationError:
        return "refused", None


def _plain_outcome(cls: Any, doc: object) -> tuple[str, Any]:
    try:
        return "ok", cls.from_api(doc).to_api()
    except PlainValidationError:
        return "refused", None


TWINS: dict[type[BaseModel], Any] = {m: getattr(plain, m.__name__) for m in MODELS} | {
    m: getattr(state_plain, m.__name__) for m in state_model.MODELS
}
"""Each pydantic model and the plain class generated from it."""


def _same(model: type[BaseModel], doc: object) -> None:
    cls = TWINS[model]
    assert _plain_outcome(cls, doc) == _outcome(model, doc), (model.__name__, doc)


ODD_VALUES = st.sampled_from(
    [
        None,
        True,
        False,
        0,
        1,
        -1,
        2,
        1.0,
        1.5,
        60.0,
        255,
        256,
        65535,
        10**6,
        "",
        " ",
        "5",
        " 5 ",
        "+5",
        "1_000",
        "5.0",
        "5.5",
        "x",
        "yes",
        "off",
        "true",
        "px4",
        "PX4",
        "Land",
        "OK",
        "fc1",
        "fc-1",
        "Fc1",
        "a" * 70,
        "127.0.0.1:14550",
        "host:99999",
        "2026-05-01T12:00:00Z",
        "2026-05-01T12:00:00",
        [],
        [1],
        {},
        float("nan"),
        float("inf"),
    ]
)


def _mutations(doc: dict[str, Any]) -> st.SearchStrategy[dict[str, Any]]:
    """``doc`` with one field (at any depth) removed, or replaced by an odd value."""
    paths: list[tuple[Any, ...]] = []

    def walk(node: Any, path: tuple[Any, ...]) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                paths.append((*path, key))
                walk(value, (*path, key))
        elif isinstance(node, list):
            for i, value in enumerate(node):
                paths.append((*path, i))
                walk(value, (*path, i))

    walk(doc, ())

    def apply(path: tuple[Any, ...], value: object, remove: bool) -> dict[str, Any]:
        copy = json.loads(json.dumps(doc))
        node = copy
        for step in path[:-1]:
            node = node[step]
        if remove and isinstance(node, dict):
            del node[path[-1]]
        else:
            node[path[-1]] = value
        return copy

    return st.builds(apply, st.sampled_from(paths), ODD_VALUES, st.booleans())


@settings(max_examples=600, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(_mutations(SPEC))
def test_the_spec_loader_accepts_and_refuses_as_the_model_does(doc: dict[str, Any]) -> None:
    _same(autopilot.RedundantAutopilotSpec, doc)


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(_mutations(STATUS))
def test_the_status_loader_accepts_and_refuses_as_the_model_does(doc: dict[str, Any]) -> None:
    _same(autopilot.RedundantAutopilotStatus, doc)


@given(st.sampled_from(list(TWINS)), ODD_VALUES)
def test_every_model_refuses_what_its_model_refuses(
    model: type[meta.ApiModel], doc: object
) -> None:
    _same(model, doc)


def test_defaults_unknown_fields_and_python_names_are_read_as_the_model_reads_them() -> None:
    doc = {**SPEC, "unknownField": 1, "failoverPolicy": {"thresholds": {"clear_ms": 5}}}
    _same(autopilot.RedundantAutopilotSpec, doc)
    _same(
        autopilot.AutopilotSpec,
        {"name": "fc1", "stack": "px4", "connection": "x", "sysid": "3", "bridge_channel": "1"},
    )
    _same(autopilot.RedundantAutopilotStatus, {})


def test_a_refusal_names_the_field() -> None:
    bad = json.loads(json.dumps(SPEC))
    bad["autopilots"][1]["sysid"] = 256
    try:
        plain.RedundantAutopilotSpec.from_api(bad)
    except PlainValidationError as exc:
        assert str(exc) == "autopilots.1.sysid: Input should be less than or equal to 255"
    else:
        raise AssertionError("sysid 256 accepted")


PYDANTIC_AGENT_STATE = {
    "spec": autopilot.RedundantAutopilotSpec.model_validate(SPEC).model_dump(
        by_alias=True, mode="json"
    ),
    "generation": None,
    "active": "fc2",
    "latched": True,
    "failedFrom": ["fc1"],
    "failoverCount": 1,
    "lastFailover": STATUS["lastFailover"] | {"standbyInStep": None},
    "commands": [
        {"id": "c-1", "result": "Executed", "message": "", "time": "2026-05-01T12:00:00Z"}
    ],
    "safety": {
        "autopilot": "fc2",
        "phase": "Holding",
        "finalAction": "Land",
        "holdSeconds": 3.0,
        "holdStarted": 1777636800.5,
        "landStarted": None,
        "holds": True,
    },
    "savedAt": "2026-05-01T12:00:02Z",
}
"""The shape the agent's pydantic PersistedState wrote (nulls included)."""

HAND_WRITTEN_AGENT_STATE = json.loads(
    Path(__file__).with_name("agent-state-hand-written-loader.json").read_text()
)
"""A file the pydantic-free agent wrote before its state classes were generated (a
landing order in progress, every optional field present)."""


def test_a_state_file_written_by_the_pydantic_agent_still_loads() -> None:
    state = PersistedState.from_api(PYDANTIC_AGENT_STATE)
    assert state.spec.to_api() == plain.RedundantAutopilotSpec.from_api(SPEC).to_api()
    assert (state.active, state.latched, state.failed_from) == ("fc2", True, ["fc1"])
    assert state.safety is not None and state.safety.hold_started == 1777636800.5
    assert PersistedState.from_api(json.loads(json.dumps(state.api_dump()))) == state


def test_a_state_file_written_by_the_hand_written_loader_still_loads() -> None:
    state = PersistedState.from_api(HAND_WRITTEN_AGENT_STATE)
    assert (state.generation, state.failover_count, state.commands[0].id) == (7, 2, "c-1")
    assert state.safety == state_plain.SafetyProgress(
        autopilot="fc2",
        phase="Landing",
        final_action=FinalAction.LAND,
        land_started=1777636801.25,
        holds=False,
    )
    # written back unchanged, apart from fields added to the spec since (their defaults)
    expected = json.loads(json.dumps(HAND_WRITTEN_AGENT_STATE))
    expected["spec"].update({"firmware": None, "parameters": None, "fence": None})
    expected["spec"]["hub"]["endpoints"] = []
    expected["spec"]["failoverPolicy"]["thresholds"].update(
        {"messageErrorMinMs": 60, "silenceMargin": 2.5}
    )
    assert state.api_dump() == expected


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(_mutations(PYDANTIC_AGENT_STATE) | _mutations(HAND_WRITTEN_AGENT_STATE))
def test_the_state_loader_accepts_and_refuses_as_its_declaration_does(
    doc: dict[str, Any],
) -> None:
    _same(state_model.PersistedState, doc)
