"""Autopilot parameters as declared state: written, read back and watched over MAVLink.

A RedundantAutopilot's ``spec.parameters`` names parameters per flight stack; the agent
keeps them on every autopilot of that stack with the MAVLink parameter protocol, one
:class:`ParamKeeper` per autopilot, stepped on the agent's heartbeat thread beside the
stream keeper (never on the decision loop: nothing here can switch an autopilot).

The protocol as the firmware speaks it (checked against recorded PX4 v1.16 and
ArduCopter traffic and the MAVLink parameter protocol):

- PARAM_REQUEST_READ by name (``param_index`` -1) is answered with one PARAM_VALUE that
  carries the value and the parameter's type; a name the firmware lacks gets no answer
  (hence :data:`MAX_READS`, then ``UnknownParameter``).
- PARAM_SET is answered with PARAM_VALUE holding the value the autopilot now has: the
  written one when it took it, its old one otherwise. A write counts only when that
  echo reads back as declared; it is repeated every :data:`RETRY_S` up to
  :data:`MAX_WRITES` times, then reported as ``WriteRefused``.
- An integer travels in PARAM_VALUE's float field in one of two encodings
  (:mod:`roost_mavlink.params`): PX4 copies the integer's bytes into the float,
  ArduPilot converts the number. The stack decides by default;
  AUTOPILOT_VERSION's capability bits decide once known. Each write uses the type the
  autopilot reported for that parameter, never one guessed from the value.
- PX4 answers a write on the link it came from only (the recorded onboard link saw no
  PARAM_VALUE when a ground station set a parameter), so a change by another client is
  found by reading back, not by listening: every held parameter is read again at least
  every :data:`READBACK_S` (at most :data:`READBACK_PER_S` reads a second). ArduPilot
  also sends changed values on every link, which the keeper takes too.

What happens to one parameter is the pure :func:`decide` (decision table in
``tests/unit/test_agent_params.py``): nothing is written while any autopilot of the
vehicle is armed (``DeferredWhileArmed``); a parameter the agent set once and someone
changed since is ``Drifted`` and written back only when ``onDrift`` is ``Restore``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from enum import Enum

from roost_api.autopilot_enums import ParametersReason
from roost_api.core import ConditionStatus, Stack
from roost_mavlink.params import (
    FLOAT32_MAX,
    INT_RANGE,
    ParamType,
    bytewise_default,
    bytewise_from_capabilities,
    float32,
    from_wire,
    known_type,
    to_wire,
)

RETRY_S = 1.0
"""How long a read or write waits for its PARAM_VALUE before it is sent again."""
MAX_READS = 3
"""Reads of a name without an answer before the firmware is taken not to have it."""
MAX_WRITES = 3
"""Writes whose echo kept another value before the write counts as refused."""
WINDOW = 16
"""Reads and writes waiting for an answer at once, per autopilot (a burst of 100
PARAM_SETs would overflow a serial link's buffer)."""
READBACK_S = 1.0
"""A held parameter is read again after this long (finds changes by other clients)."""
READBACK_PER_S = 20.0
"""At most this many read-backs a second per autopilot (with many parameters the
read-back cycle stretches to ``count / READBACK_PER_S`` seconds)."""
LISTED = 3
"""Parameters a condition message names before it says how many more."""


def value_problem(value: float, ptype: ParamType) -> str | None:
    """Why ``value`` cannot be written to a parameter of type ``ptype`` (None: it can)."""
    if not math.isfinite(value):
        return f"{value} is not a finite number"
    if ptype is ParamType.REAL32:
        return None if abs(value) <= FLOAT32_MAX else f"{value} exceeds a 32-bit float"
    if value != int(value):
        return f"{value:g} is not a whole number ({ptype.name} parameter)"
    low, high = INT_RANGE[ptype]
    if not low <= value <= high:
        return f"{value:g} is outside {low}..{high} ({ptype.name} parameter)"
    return None


def same(observed: float, desired: float, ptype: ParamType) -> bool:
    """Whether the autopilot holds ``desired`` (floats compared as 32-bit floats)."""
    if ptype is ParamType.REAL32:
        return float32(observed) == float32(desired)
    return observed == desired


class Do(Enum):
    """What to send for one parameter now."""

    NOTHING = "nothing"
    READ = "read"
    WRITE = "write"


@dataclass(frozen=True)
class Facts:
    """What the keeper knows of one parameter on one autopilot (times: monotonic s)."""

    desired: float
    observed: float | None = None
    ptype: ParamType | None = None
    applied: bool = False  # it read back as declared once: a later difference is drift
    reads: int = 0  # reads sent without an answer
    read_at: float = -math.inf
    writes: int = 0  # writes whose echo did not read back as declared
    write_at: float = -math.inf


def decide(f: Facts, *, now: float, armed: bool, restore: bool) -> tuple[Do, ParametersReason]:
    """What to send for one parameter, and the reason it is reported with.

    Rules, first that applies: no answer yet → read (every :data:`RETRY_S`), after
    :data:`MAX_READS` unanswered reads ``UnknownParameter``; a value its type cannot hold
    → ``InvalidValue``; reads back as declared → ``InSync``; set once and changed since →
    ``Drifted``, written back only with ``restore`` and disarmed; armed → no write,
    ``DeferredWhileArmed``; :data:`MAX_WRITES` echoes kept another value →
    ``WriteRefused``; otherwise write (every :data:`RETRY_S`), ``Writing``.
    """
    if f.observed is None or f.ptype is None:
        if now - f.read_at < RETRY_S:
            return Do.NOTHING, ParametersReason.NO_DATA
        if f.reads >= MAX_READS:
            return Do.NOTHING, ParametersReason.MISSING
        return Do.READ, ParametersReason.NO_DATA
    if value_problem(f.desired, f.ptype) is not None:
        return Do.NOTHING, ParametersReason.INVALID
    if same(f.observed, f.desired, f.ptype):
        return Do.NOTHING, ParametersReason.IN_SYNC
    drifted = f.applied
    if drifted and not restore:
        return Do.NOTHING, ParametersReason.DRIFTED
    if armed:
        return Do.NOTHING, ParametersReason.DRIFTED if drifted else ParametersReason.DEFERRED
    if now - f.write_at < RETRY_S:
        return Do.NOTHING, ParametersReason.DRIFTED if drifted else ParametersReason.WRITING
    if f.writes >= MAX_WRITES:
        return Do.NOTHING, ParametersReason.REFUSED
    return Do.WRITE, ParametersReason.DRIFTED if drifted else ParametersReason.WRITING


# The reason a condition shows: the first of these any parameter has.
_PRECEDENCE = (
    ParametersReason.MISSING,
    ParametersReason.INVALID,
    ParametersReason.REFUSED,
    ParametersReason.DRIFTED,
    ParametersReason.DEFERRED,
    ParametersReason.WRITING,
    ParametersReason.NO_DATA,
    ParametersReason.IN_SYNC,
)


@dataclass(frozen=True)
class Read:
    """PARAM_REQUEST_READ of one name."""

    name: str


@dataclass(frozen=True)
class Write:
    """PARAM_SET of one name: the wire value and type to send."""

    name: str
    wire: float
    ptype: ParamType


@dataclass(frozen=True)
class Drift:
    """A parameter the agent set, found changed by someone else."""

    name: str
    desired: float
    observed: float


@dataclass(frozen=True)
class Verdict:
    """The ``ParametersInSync`` condition of one autopilot."""

    status: ConditionStatus
    reason: ParametersReason
    message: str


@dataclass
class _Param:
    facts: Facts
    reason: ParametersReason = ParametersReason.NO_DATA
    waiting_since: float | None = None  # a read or write awaits its PARAM_VALUE
    seen_at: float = -math.inf  # the last PARAM_VALUE for it


def _number(value: float) -> str:
    return f"{value:g}"


class ParamKeeper:
    """The declared parameters of one autopilot and what it holds (not thread-safe: the
    agent's heartbeat thread is its only user)."""

    def __init__(self, stack: Stack) -> None:
        self.stack = Stack(stack)
        self.bytewise = bytewise_default(self.stack)
        self._params: dict[str, _Param] = {}
        self._readback_credit = 0.0
        self._stepped_at: float | None = None

    def set_capabilities(self, capabilities: int) -> None:
        """AUTOPILOT_VERSION's capability bits: they decide the integer encoding."""
        self.bytewise = bytewise_from_capabilities(capabilities, self.stack)

    def declare(self, desired: Mapping[str, float]) -> None:
        """The parameters to keep (a changed value is a new declaration: written again,
        not drift)."""
        for name in list(self._params):
            if name not in desired:
                del self._params[name]
        for name, value in desired.items():
            known = self._params.get(name)
            if known is None:
                self._params[name] = _Param(Facts(desired=value))
            elif known.facts.desired != value:
                known.facts = replace(known.facts, desired=value, applied=False, writes=0)

    @property
    def declared(self) -> bool:
        """Whether any parameter is declared for this autopilot."""
        return bool(self._params)

    def observe(self, name: str, wire: float, raw_type: int, now: float) -> Drift | None:
        """A PARAM_VALUE from the autopilot; returns the drift it shows, if it is news."""
        param = self._params.get(name)
        ptype = known_type(raw_type)
        if param is None or ptype is None:
            return None
        f = param.facts
        value = from_wire(wire, ptype, bytewise=self.bytewise)
        held = same(value, f.desired, ptype)
        was_held = (
            f.observed is not None and f.ptype is not None and same(f.observed, f.desired, f.ptype)
        )
        param.facts = replace(
            f,
            observed=value,
            ptype=ptype,
            applied=f.applied or held,
            reads=0,
            writes=0 if held else f.writes,
        )
        param.waiting_since = None
        param.seen_at = now
        if f.applied and was_held and not held:
            return Drift(name, f.desired, value)
        return None

    def step(self, now: float, *, armed: bool, restore: bool) -> list[Read | Write]:
        """The reads and writes to send now (at most :data:`WINDOW` awaiting answers)."""
        last, self._stepped_at = self._stepped_at, now
        if last is not None:
            self._readback_credit = min(
                self._readback_credit + (now - last) * READBACK_PER_S, READBACK_PER_S
            )
        busy = sum(
            1
            for p in self._params.values()
            if p.waiting_since is not None and now - p.waiting_since < RETRY_S
        )
        out: list[Read | Write] = []
        stale: list[tuple[float, str]] = []
        for name, param in self._params.items():
            f = param.facts
            do, param.reason = decide(f, now=now, armed=armed, restore=restore)
            if do is Do.NOTHING:
                if f.observed is not None and now - param.seen_at >= READBACK_S:
                    stale.append((param.seen_at, name))
                continue
            if busy >= WINDOW:
                continue
            busy += 1
            param.waiting_since = now
            if do is Do.READ:
                param.facts = replace(f, reads=f.reads + 1, read_at=now)
                out.append(Read(name))
            else:
                assert f.ptype is not None
                param.facts = replace(f, writes=f.writes + 1, write_at=now)
                wire = to_wire(f.desired, f.ptype, bytewise=self.bytewise)
                out.append(Write(name, wire, f.ptype))
        for _, name in sorted(stale):
            param = self._params[name]
            if busy >= WINDOW or self._readback_credit < 1:
                break
            if param.waiting_since is not None and now - param.waiting_since < RETRY_S:
                continue
            busy += 1
            self._readback_credit -= 1
            param.waiting_since = now
            param.seen_at = now  # read again one READBACK_S later, answered or not
            out.append(Read(name))
        return out

    def verdict(self) -> Verdict:
        """The autopilot's ``ParametersInSync`` condition as of the last step."""
        by_reason: dict[ParametersReason, list[str]] = {}
        for name, param in self._params.items():
            by_reason.setdefault(param.reason, []).append(self._describe(name, param))
        reason = next((r for r in _PRECEDENCE if r in by_reason), ParametersReason.IN_SYNC)
        if reason is ParametersReason.IN_SYNC:
            count = len(self._params)
            return Verdict("True", reason, f"{count} parameter(s) hold their declared values")
        items = by_reason[reason]
        listed = "; ".join(items[:LISTED])
        more = f" (and {len(items) - LISTED} more)" if len(items) > LISTED else ""
        status: ConditionStatus = "Unknown" if reason is ParametersReason.NO_DATA else "False"
        return Verdict(status, reason, f"{_WHAT[reason]}: {listed}{more}")

    def _describe(self, name: str, param: _Param) -> str:
        f = param.facts
        desired = _number(f.desired)
        if f.observed is None:
            return f"{name} (declared {desired})"
        if param.reason is ParametersReason.INVALID and f.ptype is not None:
            return f"{name}: {value_problem(f.desired, f.ptype)}"
        return f"{name} is {_number(f.observed)}, declared {desired}"

    def reasons(self) -> dict[str, ParametersReason]:
        """Each declared parameter's reason as of the last step."""
        return {name: p.reason for name, p in self._params.items()}

    def observed(self) -> dict[str, float | None]:
        """Each declared parameter's value as last read (None: not read yet)."""
        return {name: p.facts.observed for name, p in self._params.items()}


_WHAT = {
    ParametersReason.MISSING: "the firmware has no such parameter",
    ParametersReason.INVALID: "the declared value does not fit the parameter",
    ParametersReason.REFUSED: "the autopilot kept another value after repeated writes",
    ParametersReason.DRIFTED: "changed on the autopilot since the agent set it",
    ParametersReason.DEFERRED: "written once the vehicle is disarmed",
    ParametersReason.WRITING: "being written",
    ParametersReason.NO_DATA: "not read yet",
}


def nothing_declared(keepers: Iterable[ParamKeeper], verdicts: Mapping[str, object]) -> bool:
    """Whether, with no parameters in the spec, stepping the agent's keepers would change
    nothing and send nothing: no keeper holds a declaration (the values received are
    read only for declared parameters; a new link's keeper starts empty) and no
    ParametersInSync verdict is left to withdraw. The heartbeat round then skips them."""
    return not verdicts and not any(keeper.declared for keeper in keepers)


__all__ = [
    "Do",
    "Drift",
    "Facts",
    "ParamKeeper",
    "ParamType",
    "Read",
    "Verdict",
    "Write",
    "bytewise_from_capabilities",
    "decide",
    "from_wire",
    "nothing_declared",
    "same",
    "to_wire",
    "value_problem",
]
