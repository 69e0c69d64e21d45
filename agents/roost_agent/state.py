"""What the agent keeps on disk so that a restart mid-flight changes nothing.

A drone cannot wait for the API server, and an agent restarted in flight (crash, OOM
kill, update) must not switch back to an autopilot it failed over from. So the agent
writes its last applied spec and the decision state that must outlive it (the active
autopilot, the latch, which autopilots were failed from, the last failover and the ids
of commands already executed, and how far the safety routine got) to one JSON file,
atomically: a temporary file in the same
directory, fsync, rename over the old one, fsync the directory. A reader sees either the
old or the new file, never half of one. A corrupt file is moved aside, not trusted.
"""

from __future__ import annotations

import json
import logging
import os
from datetime import datetime
from pathlib import Path

from pydantic import Field, ValidationError

from roost_api.autopilot import (
    CommandResult,
    FailoverRecord,
    FinalAction,
    RedundantAutopilotSpec,
)
from roost_api.meta import ApiModel

log = logging.getLogger(__name__)

STATE_FILE_NAME = "agent-state.json"
MAX_REMEMBERED_COMMANDS = 64


class SafetyProgress(ApiModel):
    """How far the safety routine (or a landing order) got; resumed after a restart."""

    autopilot: str = Field(description="Autopilot the routine runs on.")
    phase: str = Field(description="Last phase reached (safety.Phase value).")
    final_action: FinalAction = Field(description="The final action it is heading for.")
    hold_seconds: float = Field(default=0.0, description="Hold length asked for.")
    hold_started: float | None = Field(
        default=None, description="Unix time the hold mode was confirmed."
    )
    land_started: float | None = Field(
        default=None, description="Unix time the land mode was confirmed."
    )
    holds: bool = Field(default=True, description="False for a landing order (no hold).")


class PersistedState(ApiModel):
    """The agent's durable state (camelCase JSON, like the API)."""

    spec: RedundantAutopilotSpec = Field(description="The last spec the agent applied.")
    generation: int | None = Field(default=None, description="Its metadata.generation.")
    active: str = Field(description="Autopilot connected to the motors.")
    latched: bool = Field(default=False, description="A failover happened; no automatic return.")
    failed_from: list[str] = Field(
        default_factory=list, description="Autopilots left by automatic failover."
    )
    failover_count: int = Field(default=0, description="Switches so far.")
    last_failover: FailoverRecord | None = Field(default=None, description="The last switch.")
    commands: list[CommandResult] = Field(
        default_factory=list, description="Recently executed commands, oldest first."
    )
    safety: SafetyProgress | None = Field(
        default=None, description="The safety routine in progress, or its last phase."
    )
    saved_at: datetime = Field(description="When this was written.")


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
            return PersistedState.model_validate(json.loads(text))
        except (ValueError, ValidationError) as exc:
            aside = self.path.with_name(self.path.name + ".corrupt")
            log.error("state file %s is unreadable (%s); moved to %s", self.path, exc, aside)
            self.path.replace(aside)
            return None

    def save(self, state: PersistedState) -> None:
        """Write ``state`` so that a crash at any instant leaves the old or the new file."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = json.dumps(state.model_dump(by_alias=True, mode="json"), indent=1).encode()
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
