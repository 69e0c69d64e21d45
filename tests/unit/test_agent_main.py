"""The agent's command line: the ``--autopilot`` flag and the config file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from roost_agent.main import load_spec, parse_autopilot
from tests.support.agentspec import SPEC


def test_autopilot_flag() -> None:
    spec = parse_autopilot(
        "name=fc1,stack=ardupilot,connection=tcp://127.0.0.1:5760,sysid=3,channel=1"
    )
    assert (spec.name, spec.stack, spec.sysid, spec.bridge_channel) == ("fc1", "ardupilot", 3, 1)
    with pytest.raises(Exception, match="bad --autopilot"):
        parse_autopilot("name=fc1,stack=px5,connection=udp://:1,sysid=1,channel=0")


def test_config_file_takes_a_whole_object_or_a_bare_spec(tmp_path: Path) -> None:
    whole = tmp_path / "ra.yaml"
    whole.write_text(
        json.dumps(
            {"kind": "RedundantAutopilot", "metadata": {"generation": 4}, "spec": SPEC.to_api()}
        )
    )
    spec, generation = load_spec(whole)
    assert (spec.to_api(), generation) == (SPEC.to_api(), 4)
    bare = tmp_path / "spec.json"
    bare.write_text(json.dumps(SPEC.to_api()))
    spec, generation = load_spec(bare)
    assert (spec.to_api(), generation) == (SPEC.to_api(), None)
