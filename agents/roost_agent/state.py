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
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from roost_api import plain_check as check
from roost_api.autopilot_enums import FinalAction
from roost_api.plain import CommandResult, FailoverRecord, RedundantAutopilotSpec

log = logging.getLogger(__name__)

STATE_FILE_NAME = "agent-state.json"
MAX_REMEMBERED_COMMANDS = 64


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyProgress:
    """How far the safety routine (or a landing order) got; resumed after a restart."""

    autopilot: str  # autopilot the routine runs on
    phase: str  # last phase reached (safety.Phase value)
    final_action: FinalAction  # the final action it is heading for
    hold_seconds: float = 0.0  # hold length asked for
    hold_started: float | None = None  # Unix time the hold mode was confirmed
    land_started: float | None = None  # Unix time the land mode was confirmed
    holds: bool = True  # False for a landing order (no hold)

    @classmethod
    def from_api(cls, doc: object, at: str = "") -> SafetyProgress:
        """Read the camelCase form :meth:`api_dump` writes."""
        d = check.mapping(doc, at.rstrip("."), "SafetyProgress")

        def opt_number(alias: str, name: str) -> float | None:
            v = check.get(d, alias, name)
            return None if v is None or v is check.MISSING else check.number(v, at + alias)

        v = check.get(d, "holdSeconds", "hold_seconds")
        hold_seconds = 0.0 if v is check.MISSING else check.number(v, at + "holdSeconds")
        v = check.get(d, "holds", "holds")
        return cls(
            autopilot=check.text(
                check.required(d.get("autopilot", check.MISSING), at + "autopilot"),
                at + "autopilot",
            ),
            phase=check.text(
                check.required(d.get("phase", check.MISSING), at + "phase"), at + "phase"
            ),
            final_action=check.member(
                check.required(check.get(d, "finalAction", "final_action"), at + "finalAction"),
                at + "finalAction",
                FinalAction,
            ),
            hold_seconds=hold_seconds,
            hold_started=opt_number("holdStarted", "hold_started"),
            land_started=opt_number("landStarted", "land_started"),
            holds=True if v is check.MISSING else check.boolean(v, at + "holds"),
        )

    def api_dump(self) -> dict[str, Any]:
        """Every field by its camelCase name, None included."""
        return {
            "autopilot": self.autopilot,
            "phase": self.phase,
            "finalAction": self.final_action.value,
            "holdSeconds": self.hold_seconds,
            "holdStarted": self.hold_started,
            "landStarted": self.land_started,
            "holds": self.holds,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class PersistedState:
    """The agent's durable state (camelCase JSON, like the API)."""

    spec: RedundantAutopilotSpec  # the last spec the agent applied
    generation: int | None = None  # its metadata.generation
    active: str  # autopilot connected to the motors
    latched: bool = False  # a failover happened; no automatic return
    failed_from: list[str] = field(default_factory=list)  # left by automatic failover
    failover_count: int = 0  # switches so far
    last_failover: FailoverRecord | None = None  # the last switch
    commands: list[CommandResult] = field(default_factory=list)  # executed, oldest first
    safety: SafetyProgress | None = None  # the safety routine in progress, or its last phase
    saved_at: datetime  # when this was written

    @classmethod
    def from_api(cls, doc: object) -> PersistedState:
        """Read the file's JSON (written by :meth:`api_dump`, or by the agent's earlier
        pydantic model of the same shape)."""
        d = check.mapping(doc, "", "PersistedState")

        def present(alias: str, name: str) -> object | None:
            v = check.get(d, alias, name)
            return None if v is check.MISSING else v

        generation = present("generation", "generation")
        last_failover = present("lastFailover", "last_failover")
        safety = present("safety", "safety")
        return cls(
            spec=RedundantAutopilotSpec.from_api(
                check.required(d.get("spec", check.MISSING), "spec"), "spec."
            ),
            generation=None if generation is None else check.integer(generation, "generation"),
            active=check.text(check.required(d.get("active", check.MISSING), "active"), "active"),
            latched=check.boolean(present("latched", "latched") or False, "latched"),
            failed_from=check.items(
                present("failedFrom", "failed_from") or [], "failedFrom", check.text
            ),
            failover_count=check.integer(
                present("failoverCount", "failover_count") or 0, "failoverCount"
            ),
            last_failover=None
            if last_failover is None
            else FailoverRecord.from_api(last_failover, "lastFailover."),
            commands=check.items(
                present("commands", "commands") or [],
                "commands",
                lambda v, w: CommandResult.from_api(v, w + "."),
            ),
            safety=None if safety is None else SafetyProgress.from_api(safety, "safety."),
            saved_at=check.moment(
                check.required(check.get(d, "savedAt", "saved_at"), "savedAt"), "savedAt"
            ),
        )

    def api_dump(self) -> dict[str, Any]:
        """Every field by its camelCase name, None included."""
        return {
            "spec": self.spec.api_dump(),
            "generation": self.generation,
            "active": self.active,
            "latched": self.latched,
            "failedFrom": list(self.failed_from),
            "failoverCount": self.failover_count,
            "lastFailover": None if self.last_failover is None else self.last_failover.api_dump(),
            "commands": [c.api_dump() for c in self.commands],
            "safety": None if self.safety is None else self.safety.api_dump(),
            "savedAt": check.iso(self.saved_at),
        }


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
