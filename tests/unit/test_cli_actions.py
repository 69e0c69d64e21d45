"""The decisions behind `roost abort`, `roost estop` and finding the cluster, without a cluster.

The e-stop path force-disarms vehicles, so which RedundantAutopilots it addresses and how
it reads the agents' answers are tested here as a table; the e2e sandbox test sends a
real one through the API server to a real agent.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from roost_api.autopilot import AutopilotCommand, CommandAction, RedundantAutopilotSpec
from roost_api.commands import command_patch, new_command
from roost_api.resources import MISSION, REDUNDANT_AUTOPILOT, VEHICLE, ResourceKind
from roost_cli import actions
from roost_cli.cluster import NO_CLUSTER, api_error, resolve_kubeconfig
from roost_cli.errors import CliError
from roost_kube.errors import error_for_status

AT = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)


def test_every_command_gets_a_fresh_id_even_when_repeated() -> None:
    first = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    second = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    assert first.id != second.id
    assert first.id.startswith("emergencystop-20260501120000-")
    assert len(first.id) <= 64


def test_only_a_switch_names_a_target() -> None:
    switch = new_command(CommandAction.SWITCH, target="fc-b", issued_at=AT)
    assert switch.target == "fc-b"
    with pytest.raises(ValueError, match="Switch command needs a target"):
        new_command(CommandAction.SWITCH)
    with pytest.raises(ValueError, match="other commands take none"):
        new_command(CommandAction.EMERGENCY_STOP, target="fc-b")


def test_the_command_patch_is_camel_case_and_fits_the_spec_model() -> None:
    command = new_command(CommandAction.SAFETY_ROUTINE, issued_at=AT, deadline_seconds=5)
    patch = command_patch(command)
    assert patch == {
        "spec": {
            "command": {
                "id": command.id,
                "action": "SafetyRoutine",
                "issuedAt": "2026-05-01T12:00:00Z",
                "deadlineSeconds": 5,
            }
        }
    }
    spec = RedundantAutopilotSpec.model_validate(
        {
            "vehicleName": "d1",
            "primary": "a",
            "autopilots": [
                {
                    "name": n,
                    "stack": "px4",
                    "connection": "udp://:1",
                    "sysid": i,
                    "bridgeChannel": i,
                }
                for i, n in enumerate("ab", start=1)
            ],
            **patch["spec"],
        }
    )
    assert spec.command == command


@pytest.mark.parametrize(
    ("ref", "expected"),
    [("survey", ("default", "survey")), ("lab/survey", ("lab", "survey"))],
)
def test_mission_references_take_an_optional_namespace(ref: str, expected: tuple[str, str]) -> None:
    assert actions.split_mission_ref(ref, "default") == expected


@pytest.mark.parametrize("ref", ["/survey", "lab/"])
def test_a_half_mission_reference_is_refused(ref: str) -> None:
    with pytest.raises(CliError, match="NAMESPACE/NAME"):
        actions.split_mission_ref(ref, "default")


RAS = [
    {"metadata": {"name": "d1"}, "spec": {"vehicleName": "d1"}},
    {"metadata": {"name": "ra-of-d2"}, "spec": {"vehicleName": "d2"}},
    {"metadata": {"name": "d3"}, "spec": {}},
]


def test_autopilots_are_found_by_the_vehicle_they_fly() -> None:
    assert actions.autopilots_by_vehicle(RAS) == {"d1": "d1", "d2": "ra-of-d2", "d3": "d3"}


@pytest.mark.parametrize(
    ("vehicles", "everything", "expected"),
    [
        (["d2"], False, {"d2": "ra-of-d2"}),
        (["d3", "d1"], False, {"d3": "d3", "d1": "d1"}),
        ([], True, {"d1": "d1", "d2": "ra-of-d2", "d3": "d3"}),
    ],
)
def test_estop_addresses_exactly_the_named_vehicles_or_all(
    vehicles: list[str], everything: bool, expected: dict[str, str]
) -> None:
    by_vehicle = actions.autopilots_by_vehicle(RAS)
    assert actions.select_targets(by_vehicle, vehicles, everything) == expected


@pytest.mark.parametrize(("vehicles", "everything"), [([], False), (["d1"], True)])
def test_estop_needs_vehicles_or_all_but_not_both(vehicles: list[str], everything: bool) -> None:
    with pytest.raises(CliError, match="--vehicle NAME"):
        actions.select_targets({"d1": "d1"}, vehicles, everything)


def test_estop_of_an_unknown_vehicle_fails_before_stopping_anything() -> None:
    with pytest.raises(CliError, match="no RedundantAutopilot for vehicle ghost"):
        actions.select_targets({"d1": "d1"}, ["d1", "ghost"], False)


def test_estop_all_on_an_empty_fleet_says_so() -> None:
    with pytest.raises(CliError, match="nothing to stop"):
        actions.select_targets({}, [], True)


SPEC: dict[str, Any] = {
    "vehicleName": "d2",
    "primary": "a",
    "autopilots": [
        {"name": n, "stack": "px4", "connection": "udp://:1", "sysid": i, "bridgeChannel": i}
        for i, n in enumerate("ab", start=1)
    ],
}


def _ra(
    spec_command: AutopilotCommand | None,
    answered: AutopilotCommand | None = None,
    result: str = "Executed",
) -> dict[str, object]:
    status: dict[str, object] = {}
    if answered is not None:
        status["lastCommand"] = {
            "id": answered.id,
            "result": result,
            "message": "disarmed fc-b",
            "time": (AT + timedelta(seconds=1)).isoformat(),
        }
    spec: dict[str, Any] = dict(SPEC)
    if spec_command is not None:
        spec["command"] = spec_command.to_api()
    return {"metadata": {"name": "ra-of-d2"}, "spec": spec, "status": status}


def test_a_command_still_in_the_spec_and_unanswered_is_pending() -> None:
    mine = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    older = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    assert actions.acknowledgement("d2", _ra(mine), mine) is None
    assert actions.acknowledgement("d2", _ra(mine, answered=older), mine) is None


@pytest.mark.parametrize("result", ["Executed", "Rejected", "Expired"])
def test_the_agents_answer_to_this_id_is_the_outcome(result: str) -> None:
    mine = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    ack = actions.acknowledgement("d2", _ra(mine, answered=mine, result=result), mine)
    assert ack == actions.Acknowledgement("d2", "ra-of-d2", mine.id, result, "disarmed fc-b")


def test_a_command_replaced_before_the_agent_saw_it_is_superseded() -> None:
    mine = new_command(CommandAction.EMERGENCY_STOP, issued_at=AT)
    newer = new_command(CommandAction.SAFETY_ROUTINE, issued_at=AT)
    ack = actions.acknowledgement("d2", _ra(newer), mine)
    assert ack is not None
    assert (ack.result, ack.message) == ("Superseded", "")


def test_the_kubeconfig_comes_from_the_flag_then_env_then_sandbox_then_home(
    tmp_path: Path,
) -> None:
    files = {name: tmp_path / name for name in ("flag", "env", "sandbox")}
    for path in files.values():
        path.write_text("")
    home = tmp_path / "home"
    (home / ".kube").mkdir(parents=True)
    (home / ".kube" / "config").write_text("")
    env = {"KUBECONFIG": f"{files['env']}:/elsewhere"}

    def pick(explicit: Path | None, environ: dict[str, str], sandbox: Path | None) -> str:
        return resolve_kubeconfig(explicit, environ, sandbox, home).source

    assert pick(files["flag"], env, files["sandbox"]) == "--kubeconfig"
    assert pick(None, env, files["sandbox"]) == "$KUBECONFIG"
    assert pick(None, {}, files["sandbox"]) == "sandbox"
    assert pick(None, {"KUBECONFIG": ""}, None) == "~/.kube/config"


def test_no_cluster_at_all_says_how_to_get_one(tmp_path: Path) -> None:
    with pytest.raises(CliError) as error:
        resolve_kubeconfig(None, {}, None, tmp_path)
    assert str(error.value) == NO_CLUSTER
    assert "roost sandbox up" in NO_CLUSTER and "KUBECONFIG" in NO_CLUSTER


def test_a_named_kubeconfig_that_does_not_exist_is_an_error_not_a_fallback(
    tmp_path: Path,
) -> None:
    with pytest.raises(CliError, match=r"KUBECONFIG=.*does not exist"):
        resolve_kubeconfig(None, {"KUBECONFIG": str(tmp_path / "nope")}, None, tmp_path)
    with pytest.raises(CliError, match=r"--kubeconfig .* does not exist"):
        resolve_kubeconfig(tmp_path / "nope", {}, None, tmp_path)


@pytest.mark.parametrize(
    ("what", "kind", "status", "expected"),
    [
        ("list vehicles", VEHICLE, 404, "Vehicle API is not installed"),
        ("patch Mission default/x", MISSION, 404, "`roost missions` lists what exists"),
        ("get RedundantAutopilot d1", REDUNDANT_AUTOPILOT, 404, "`roost status` lists"),
        ("patch Mission default/x", MISSION, 403, "forbidden thing. Use a kubeconfig"),
        ("patch Mission default/x", MISSION, 422, "rejected it: forbidden thing"),
        ("list events", None, 404, "HTTP 404 forbidden thing"),
    ],
)
def test_api_errors_say_what_to_do(
    what: str, kind: ResourceKind | None, status: int, expected: str
) -> None:
    body = json.dumps({"kind": "Status", "message": "forbidden thing"})
    error = error_for_status(status, "GET", "/apis/roost.dev", body)
    assert expected in str(api_error(what, kind, error))
