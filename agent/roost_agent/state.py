"""What the agent keeps on disk so that a restart mid-flight changes nothing.

A drone cannot wait for the API server, and an agent restarted in flight (crash, OOM
kill, update) must not switch back to an autopilot it failed over from. So the agent
writes its last applied spec and the decision state that must outlive it (the active
autopilot, the latch, which autopilots were failed from, the last failover and the ids
of commands already executed, and how far the safety routine got) to one JSON file,
atomically: a temporary file in the same
directory, fsync, rename over the old one, fsync the directory. A reader sees either the
old or the new file, never half of one. A corrupt file is moved aside, not trusted.

The file's classes, :class:`PersistedState` and :class:`SafetyProgress`, are declared in
:mod:`roost_agent.state_model` and generated into :mod:`roost_agent.state_plain` by the
generator of the API's pydantic-free classes (:mod:`roost_api.plain_gen`), so the agent
has one way of declaring a validated class and still runs without pydantic. Files
written by older agents have the same shape as the declaration and load unchanged.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from roost_agent.state_plain import PersistedState, SafetyProgress

__all__ = [
    "MAX_REMEMBERED_COMMANDS",
    "STATE_FILE_NAME",
    "PersistedState",
    "SafetyProgress",
    "StateFile",
]

log = logging.getLogger(__name__)

STATE_FILE_NAME = "agent-state.json"
MAX_REMEMBERED_COMMANDS = 64


class StateFile:
    """Atomic load/save of :class:`PersistedState` at one path."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def load(self) -> PersistedState | None:
        """The saved state, or None when there is none or it cannot be trusted."""
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        try:
            return PersistedState.from_api(json.loads(text))
        except ValueError as exc:  # bad JSON or a PlainValidationError
            aside = self.path.with_name(self.path.name + ".corrupt")
            log.error("state file %s is unreadable (%s); moved to %s", self.path, exc, aside)
            self.path.replace(aside)
            return None

    def save(self, state: PersistedState) -> None:
        """Write ``state`` so that a crash at any instant leaves the old or the new file."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = json.dumps(state.api_dump(), indent=1).encode()
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        tmp.replace(self.path)
        dir_fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
