"""The node agent's plain API classes (and its state file's) against the pydantic models
they are generated from.

The agent runs without pydantic (:mod:`roost_api.plain_gen` says why), so these tests
hold the generated module to its source: it must be what the generator renders now, its
loaders must accept and reject the same inputs as the models, and ``to_api`` must give
the same JSON. Inputs are drawn around every field's rules: missing and null fields,
wrong types, lax forms pydantic converts (numeric strings, integral floats, ``"yes"``),
values at and beyond each bound, enum values and near misses, unknown fields.
"""

from __future__ import annotations

import json
import subprocess
import sys
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
from roost_api.plain_gen import MODELS, TARGET, render, render_declared

SPEC = {
    "vehicleName": "v1",
    "primary": "fc1",
    "autopilots": [
        {
            "name": "fc1",
            "stack": "px4",
            "connection": "udp://127.0.0.1:14541",
            "sysid": 1,
            "bridgeChannel": 0,
        },
        {
            "name": "fc2",
            "stack": "ardupilot",
            "connection": "udp://127.0.0.1:14542",
            "sysid": 2,
            "bridgeChannel": 1,
            "componentId": 1,
            "fcuUrl": "udp://:1@127.0.0.1:2",
        },
    ],
    "failoverPolicy": {"thresholds": {"messageWarnMs": 100}, "safetyRoutine": {}},
    "command": {
        "id": "c-1",
        "action": "Switch",
        "target": "fc2",
        "issuedAt": "2026-05-01T12:00:00Z",
    },
    "hub": {"tcp": "127.0.0.1:5760", "standbyLimits": {"positionM": 2}},
}
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


def test_the_committed_module_is_what_the_generator_renders() -> None:
    """Regenerate with ``python -m roost_api.plain_gen`` when this fails."""
    assert TARGET.read_text() == render()


def test_the_committed_state_module_is_what_the_generator_renders() -> None:
    """Regenerate with ``python -m roost_api.plain_gen roost_agent.state_model``."""
    target, text = render_declared("roost_agent.state_model")
    assert target == state_model.TARGET
    assert target.read_text() == text


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
    expected["spec"].update({"firmware": None, "parameters": None})
    expected["spec"]["hub"]["endpoints"] = []
    assert state.api_dump() == expected


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(_mutations(PYDANTIC_AGENT_STATE) | _mutations(HAND_WRITTEN_AGENT_STATE))
def test_the_state_loader_accepts_and_refuses_as_its_declaration_does(
    doc: dict[str, Any],
) -> None:
    _same(state_model.PersistedState, doc)


def _probe(code: str, *args: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


def test_the_standalone_agent_never_imports_pydantic() -> None:
    """pydantic costs a companion computer ~15 MB with the models, plus libcrypto
    (hashlib, via secrets) which the agent maps only with MAVLink signing on."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent, roost_agent.hub, roost_agent.state; "
        "print(sorted(m for m in ('pydantic', 'pydantic_core', 'hashlib', 'decimal') "
        "if m in sys.modules))"
    )
    assert _probe(probe) == "[]"


def test_a_standalone_agent_run_loads_neither_pydantic_nor_libcrypto(tmp_path: Path) -> None:
    """A real run: spec from a config file, two autopilot links, a saved state, status out."""
    config = tmp_path / "spec.json"
    spec = json.loads(json.dumps(SPEC))
    del spec["command"], spec["hub"]
    config.write_text(json.dumps(spec))
    probe = (
        "import sys, threading, roost_agent.main as m; "
        "threading.Timer(1.5, lambda: __import__('os').kill(__import__('os').getpid(), 15))"
        ".start(); "
        "code = m.main(['--config', sys.argv[1], '--state-dir', sys.argv[2], "
        "'--status-interval', '0.2']); "
        "maps = open('/proc/self/maps').read(); "
        "print('pydantic' in sys.modules, 'pydantic_core' in maps, 'libcrypto' in maps, "
        "file=sys.stderr)"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, str(config), str(tmp_path / "state")],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert out.stderr.strip().splitlines()[-1] == "False False False", out.stderr
    assert (tmp_path / "state" / "agent-state.json").exists()
    assert '"status"' in out.stdout
