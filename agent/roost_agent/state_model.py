"""The declaration of the agent's state file, from which :mod:`roost_agent.state_plain` is
generated: do not import at run time.

The state file (:mod:`roost_agent.state`) is read and written by the standalone agent,
which runs without pydantic, so its classes are frozen dataclasses with loaders like the
API's plain twins. Rather than a second, hand-written way of declaring such a class,
they are declared here as pydantic models (the shape the agent's state file has always
had) and written out by the same generator as :mod:`roost_api.plain`: ``python -m
roost_api.plain_gen roost_agent.state_model``. ``tests/unit/test_api_plain.py`` fails
while the generated module differs from what this renders, and checks that the loaders
accept and refuse what these models do.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

from pydantic import Field

from roost_api.autopilot import (
    CommandResult,
    FailoverRecord,
    FinalAction,
    RedundantAutopilotSpec,
)
from roost_api.meta import ApiModel


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


MODELS = (SafetyProgress, PersistedState)
"""The models to write out, each after the models it contains."""
TARGET = Path(__file__).with_name("state_plain.py")
