"""A Mission's geofence on every autopilot: saved, uploaded, read back, restored.

The operator writes the fence of the Mission that holds a vehicle into its
RedundantAutopilot's ``spec.fence`` (``roost_operator.missions``), the way it writes an
abort command there: the agent reads only its RedundantAutopilot. One
:class:`FenceKeeper` per autopilot then walks the fence through, stepped on the agent's
heartbeat thread beside the parameter keeper (nothing here can switch an autopilot):

1. **save**: download the fence the autopilot holds (MISSION_REQUEST_LIST, fence type)
   and read the stack's fence parameters, to put them back after the Mission;
2. **upload** the Mission's items (:mod:`roost_mavlink.fence`), then **verify**: download
   them again and compare item by item;
3. **parameters**: write the stack's fence parameters (altitude limit, breach action,
   enable) with the parameter keeper's confirmed writes, until they read back;
4. **held**: the ``FenceInSync`` condition is True and names the fence's id, which the
   Mission's preflight requires of every autopilot, standbys included; the parameters
   are read back as the parameter keeper does (a changed one is reported and written
   back once disarmed) and the items every :data:`REVERIFY_S`;
5. once ``spec.fence`` goes: **restore** the saved items and parameters, then drop the
   condition.

Nothing is written while any autopilot of the vehicle is armed (``DeferredWhileArmed``):
the Mission's preflight applies the fence before it arms. A failed step (refused upload,
no answer, a read-back that differs, a parameter that does not take) is reported once
with the reason and stays failed until the fence changes: the Mission's preflight then
keeps that vehicle on the ground, so no vehicle starts with a half-applied fence. The
pure step function is :meth:`FenceKeeper.step`; its decision table is in
``tests/unit/test_agent_fence.py``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any, Protocol

from roost_agent.params import ParamKeeper, Read, Write
from roost_api.autopilot_enums import FenceReason, ParametersReason
from roost_api.core import ConditionStatus, Stack
from roost_api.fence import Area, FenceAction, LatLon, held_message
from roost_api.plain import AssignedFence
from roost_mavlink.fence import (
    Item,
    Message,
    Outcome,
    Transfer,
    items_for,
    mismatch,
    stack_param_names,
    stack_params,
)

REVERIFY_S = 10.0
"""A held fence's items are read back this often (another client may upload one)."""


class Phase(Enum):
    """Where one autopilot's fence stands."""

    IDLE = "idle"  # no fence declared, nothing to restore
    SAVE_ITEMS = "save-items"
    SAVE_PARAMS = "save-params"
    UPLOAD = "upload"
    VERIFY = "verify"
    PARAMS = "params"
    HELD = "held"
    RESTORE_ITEMS = "restore-items"
    RESTORE_PARAMS = "restore-params"
    FAILED = "failed"


@dataclass(frozen=True)
class Target:
    """The fence to hold: its id, items and the stack's parameter values."""

    id: str
    items: tuple[Item, ...]
    params: dict[str, float]
    summary: str
    area: Area


def target_of(assigned: AssignedFence, stack: Stack) -> Target:
    """What ``spec.fence`` asks of an autopilot of ``stack``."""
    f = assigned.fence
    if f.circle is not None:
        c = f.circle
        area = Area(centre=LatLon(c.latitude, c.longitude), radius_m=c.radius_m)
        shape = f"circle of {c.radius_m:g} m"
    else:
        area = Area(polygon=tuple(LatLon(p.latitude, p.longitude) for p in f.polygon))
        shape = f"polygon of {len(items_for(area))} vertices"
    action = FenceAction(f.action)
    params = {p.name: p.value for p in stack_params(stack, f.max_altitude_m, action)}
    summary = f"{shape}, max altitude {f.max_altitude_m:g} m, on breach {action.value}"
    return Target(assigned.id, tuple(items_for(area)), params, summary, area)


@dataclass(frozen=True)
class Verdict:
    """The ``FenceInSync`` condition of one autopilot."""

    status: ConditionStatus
    reason: FenceReason
    message: str


@dataclass(frozen=True)
class Send:
    """A mission protocol message to send to the autopilot."""

    message: Message


Op = Send | Read | Write


class FenceKeeper:
    """The fence of one autopilot (not thread-safe: the heartbeat thread is its user)."""

    def __init__(self, stack: Stack) -> None:
        self.stack = Stack(stack)
        self.phase = Phase.IDLE
        self.target: Target | None = None
        self.previous_items: list[Item] | None = None
        self.previous_params: dict[str, float] | None = None
        self._params = ParamKeeper(self.stack)
        self._transfer: Transfer | None = None
        self._failure: tuple[FenceReason, str] | None = None
        self._deferred = False
        self.position: LatLon | None = None  # the vehicle's, where the autopilot knows it
        self._verified_at = -math.inf  # when the items last read back as uploaded

    @property
    def transferring(self) -> bool:
        """Whether a fence transfer waits for the autopilot."""
        return self._transfer is not None

    @property
    def at_rest(self) -> bool:
        """Idle with no fence: stepped with none declared and nothing received, the
        keeper sends nothing, reports nothing and stays as it is."""
        return (
            self.phase is Phase.IDLE
            and self.target is None
            and self._transfer is None
            and not self._deferred
        )

    def set_capabilities(self, capabilities: int) -> None:
        """AUTOPILOT_VERSION's capability bits (the parameters' integer encoding)."""
        self._params.set_capabilities(capabilities)

    def declare(self, target: Target | None) -> None:
        """The fence to hold (None: none; the saved one is restored)."""
        if target == self.target:
            return
        self.target = target
        self._transfer = None
        self._failure = None
        if target is None:
            self.phase = Phase.RESTORE_ITEMS if self.previous_items is not None else Phase.IDLE
        elif self.previous_items is None:
            self.phase = Phase.SAVE_ITEMS
        else:
            self.phase = Phase.UPLOAD  # a new fence over one already saved from

    def observe_param(self, name: str, wire: float, raw_type: int, now: float) -> None:
        """A PARAM_VALUE from the autopilot."""
        self._params.observe(name, wire, raw_type, now)

    def receive(self, name: str, fields: dict[str, object], now: float) -> list[Op]:
        """A mission protocol message from the autopilot; returns what to send."""
        if self._transfer is None:
            return []
        return [Send(m) for m in self._transfer.receive(name, dict(fields), now)]

    def _fail(self, reason: FenceReason, detail: str) -> list[Op]:
        self.phase = Phase.FAILED
        self._failure = (reason, detail)
        self._transfer = None
        return []

    def _run(self, make: Transfer, now: float) -> list[Op]:
        self._transfer = make
        return [Send(m) for m in make.start(now)]

    def _transfer_step(self, now: float) -> tuple[Transfer | None, list[Op]]:
        """The running transfer once it has finished (else None) and its repeats."""
        t = self._transfer
        assert t is not None
        sent: list[Op] = [Send(m) for m in t.step(now)]
        if t.outcome is Outcome.RUNNING:
            return None, sent
        self._transfer = None
        return t, sent

    def step(self, now: float, *, armed: bool) -> list[Op]:
        """What to send now; moves through the phases of the module docstring."""
        writes = self.phase in (
            Phase.UPLOAD,
            Phase.PARAMS,
            Phase.RESTORE_ITEMS,
            Phase.RESTORE_PARAMS,
        )
        self._deferred = armed and writes and self._transfer is None
        if self._deferred:
            return []
        handler = _PHASES.get(self.phase)
        return [] if handler is None else handler(self, now, armed)

    # -- one method per phase ----------------------------------------------------------

    def _await(self, now: float, make: Callable[[], Transfer], what: str) -> Transfer | list[Op]:
        """Run one transfer to its end: what to send while it runs, then the finished
        transfer (a failed one fails the phase, reported as ``what: why``)."""
        if self._transfer is None:
            return self._run(make(), now)
        done, sent = self._transfer_step(now)
        if done is None:
            return sent
        if done.outcome is not Outcome.DONE:
            return self._fail(_failure_reason(done), f"{what}: {done.detail}")
        return done

    def _save_items(self, now: float, armed: bool) -> list[Op]:
        done = self._await(now, Transfer.download, "reading the current fence")
        if isinstance(done, list):
            return done
        self.previous_items = list(done.received)
        self.phase = Phase.SAVE_PARAMS
        assert self.target is not None
        self._params.declare(self.target.params)
        return self._save_params(now, armed)

    def _save_params(self, now: float, armed: bool) -> list[Op]:
        # Stepped as if armed: the keeper reads every parameter but writes none yet.
        ops: list[Op] = list(self._params.step(now, armed=True, restore=False))
        reasons = self._params.reasons()
        missing = [n for n, r in reasons.items() if r is ParametersReason.MISSING]
        if missing:
            return self._fail(
                FenceReason.PARAMETERS, "the firmware has no parameter " + ", ".join(missing)
            )
        observed = self._params.observed()
        if any(v is None for v in observed.values()):
            return ops
        self.previous_params = {n: v for n, v in observed.items() if v is not None}
        self.phase = Phase.UPLOAD
        return ops

    def _upload(self, now: float, armed: bool) -> list[Op]:
        target = self.target
        assert target is not None
        at = self.position
        if self._transfer is None and at is not None and not target.area.contains(at):
            return self._fail(
                FenceReason.OUTSIDE,
                f"the vehicle is at {at.latitude:.6f},{at.longitude:.6f}, outside the "
                "fence: not uploaded (it would breach on arming)",
            )
        done = self._await(now, lambda: Transfer.upload(target.items), "uploading")
        if isinstance(done, list):
            return done
        self.phase = Phase.VERIFY
        return self._run(Transfer.download(), now)

    def _verify(self, now: float, armed: bool) -> list[Op]:
        assert self.target is not None
        done = self._await(now, Transfer.download, "reading the fence back")
        if isinstance(done, list):
            return done
        differs = mismatch(self.target.items, done.received)
        if differs is not None:
            return self._fail(FenceReason.MISMATCH, differs)
        self.phase = Phase.PARAMS
        self._verified_at = now
        self._params.declare(self.target.params)
        return self._keep_params(now, armed, Phase.HELD)

    def _keep_params(self, now: float, armed: bool, then: Phase) -> list[Op]:
        ops: list[Op] = list(self._params.step(now, armed=armed, restore=True))
        verdict = self._params.verdict()
        if verdict.reason in (
            ParametersReason.MISSING,
            ParametersReason.INVALID,
            ParametersReason.REFUSED,
        ):
            return self._fail(FenceReason.PARAMETERS, verdict.message)
        if verdict.reason is ParametersReason.IN_SYNC:
            self.phase = then
        return ops

    def _params_phase(self, now: float, armed: bool) -> list[Op]:
        return self._keep_params(now, armed, Phase.HELD)

    def _held(self, now: float, armed: bool) -> list[Op]:
        # The parameters are read back by their keeper (a changed one is reported and put
        # back once disarmed); the items are read back every REVERIFY_S.
        ops = self._keep_params(now, armed, Phase.HELD)
        if self.phase is not Phase.HELD:
            return ops
        if self._transfer is None and now - self._verified_at < REVERIFY_S:
            return ops
        done = self._await(now, Transfer.download, "reading the fence back")
        if isinstance(done, list):
            return ops + done
        self._verified_at = now
        assert self.target is not None
        differs = mismatch(self.target.items, done.received)
        if differs is not None:
            return self._fail(FenceReason.MISMATCH, f"changed on the autopilot: {differs}")
        return ops

    def _restore_items(self, now: float, armed: bool) -> list[Op]:
        previous = self.previous_items or []
        done = self._await(now, lambda: Transfer.upload(previous), "restoring the previous fence")
        if isinstance(done, list):
            return done
        self.phase = Phase.RESTORE_PARAMS
        self._params.declare(self.previous_params or {})
        return self._restore_params(now, armed)

    def _restore_params(self, now: float, armed: bool) -> list[Op]:
        ops = self._keep_params(now, armed, Phase.IDLE)
        if self.phase is Phase.IDLE:
            self.previous_items = None
            self.previous_params = None
            self._params.declare({})
        return ops

    # -- the condition -----------------------------------------------------------------

    def verdict(self) -> Verdict | None:
        """The autopilot's ``FenceInSync`` condition (None: nothing to report)."""
        restoring = self.target is None
        if self.phase is Phase.IDLE:
            return None
        if self.phase is Phase.FAILED:
            assert self._failure is not None
            reason, detail = self._failure
            return Verdict("False", reason, detail)
        if self._deferred:
            what = "restoring the previous fence" if restoring else "uploading the fence"
            return Verdict("False", FenceReason.DEFERRED, f"{what} waits until disarmed")
        params = self._params.verdict()
        if self.phase is Phase.HELD and params.reason is not ParametersReason.IN_SYNC:
            return Verdict("False", FenceReason.PARAMETERS, params.message)
        if self.phase is Phase.HELD:
            assert self.target is not None
            return Verdict(
                "True", FenceReason.HELD, held_message(self.target.id, self.target.summary)
            )
        reason, what = _PROGRESS[self.phase]
        return Verdict("Unknown", reason, what)


def _failure_reason(t: Transfer) -> FenceReason:
    return FenceReason.REFUSED if t.outcome is Outcome.REFUSED else FenceReason.NO_ANSWER


_PHASES = {
    Phase.SAVE_ITEMS: FenceKeeper._save_items,
    Phase.SAVE_PARAMS: FenceKeeper._save_params,
    Phase.UPLOAD: FenceKeeper._upload,
    Phase.VERIFY: FenceKeeper._verify,
    Phase.PARAMS: FenceKeeper._params_phase,
    Phase.HELD: FenceKeeper._held,
    Phase.RESTORE_ITEMS: FenceKeeper._restore_items,
    Phase.RESTORE_PARAMS: FenceKeeper._restore_params,
}

_PROGRESS = {
    Phase.SAVE_ITEMS: (FenceReason.SAVING, "reading the fence it holds, to restore it later"),
    Phase.SAVE_PARAMS: (FenceReason.SAVING, "reading its fence parameters, to restore them later"),
    Phase.UPLOAD: (FenceReason.UPLOADING, "uploading the fence"),
    Phase.VERIFY: (FenceReason.VERIFYING, "reading the uploaded fence back"),
    Phase.PARAMS: (FenceReason.UPLOADING, "writing the fence parameters"),
    Phase.RESTORE_ITEMS: (FenceReason.RESTORING, "restoring the previous fence"),
    Phase.RESTORE_PARAMS: (FenceReason.RESTORING, "restoring the previous fence parameters"),
}


class FenceLink(Protocol):
    """What the fence keepers use of an autopilot link (roost_agent.link.AutopilotLink)."""

    name: str
    stack: Stack

    def heartbeat(self) -> tuple[int, int, float] | None: ...
    def read_param(self, name: str) -> bool: ...
    def write_param(self, name: str, wire: float, ptype: int) -> bool: ...
    def send_mission(self, name: str, fields: Mapping[str, Any]) -> bool: ...


Emit = Callable[[str, str, bool, str], None]
"""(reason, message, warning, autopilot): an Event for the agent to post."""


class Fences:
    """Every autopilot's :class:`FenceKeeper`, stepped on the agent's heartbeat thread;
    the ``FenceInSync`` verdicts are read by the agent's status under ``lock``."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self._keepers: dict[str, tuple[FenceLink, FenceKeeper]] = {}
        self._verdicts: dict[str, Verdict] = {}

    def transferring(self) -> bool:
        """Whether any keeper waits for a mission protocol answer."""
        return any(keeper.transferring for _, keeper in self._keepers.values())

    def verdict(self, name: str) -> Verdict | None:
        with self.lock:
            return self._verdicts.get(name)

    def at_rest(self, links: Mapping[str, FenceLink]) -> bool:
        """Whether a :meth:`step` with no fence assigned and nothing received would change
        nothing and send nothing: every link has its keeper, each idle (no fence, none
        to restore, no transfer, nothing deferred), and no verdict is reported. The
        agent's heartbeat round then leaves the step out (most rounds of most flights)."""
        if self._verdicts or self._keepers.keys() != links.keys():
            return False
        return all(
            known is links[name] and keeper.at_rest
            for name, (known, keeper) in self._keepers.items()
        )

    def keeper(self, link: FenceLink) -> FenceKeeper:
        """The link's keeper (a new link is a new keeper)."""
        known = self._keepers.get(link.name)
        if known is None or known[0] is not link:
            known = self._keepers[link.name] = (link, FenceKeeper(link.stack))
        return known[1]

    def step(
        self,
        links: Mapping[str, FenceLink],
        assigned: AssignedFence | None,
        *,
        messages: Mapping[str, list[tuple[str, dict[str, Any], float]]],
        params: Mapping[str, list[tuple[str, float, int, float]]],
        capabilities: Mapping[str, int],
        positions: Mapping[str, LatLon],
        armed: bool,
        now: float,
        emit: Emit,
    ) -> None:
        """One step of every autopilot's keeper with what its link received."""
        for name in [n for n in self._keepers if n not in links]:
            del self._keepers[name]
        for link in links.values():
            keeper = self.keeper(link)
            if link.name in capabilities:
                keeper.set_capabilities(capabilities[link.name])
            keeper.declare(None if assigned is None else target_of(assigned, link.stack))
            keeper.position = positions.get(link.name)
            for pname, wire, ptype, at in params.get(link.name, []):
                keeper.observe_param(pname, wire, ptype, at)
            ops: list[Op] = []
            for kind, fields, at in messages.get(link.name, []):
                ops += keeper.receive(kind, fields, at)
            if link.heartbeat() is not None:  # nobody to ask before the autopilot is heard
                ops += keeper.step(now, armed=armed)
            _send(link, ops)
            self._report(link.name, keeper.verdict(), emit)

    def _report(self, name: str, verdict: Verdict | None, emit: Emit) -> None:
        with self.lock:
            before = self._verdicts.get(name)
            if verdict is None:
                self._verdicts.pop(name, None)
            else:
                self._verdicts[name] = verdict
        if verdict is None:
            if before is not None:
                emit("FenceRestored", f"{name}: the previous fence is back", False, name)
            return
        if before is None or (before.status, before.reason) != (verdict.status, verdict.reason):
            emit(
                f"Fence{verdict.reason.value}",
                f"{name}: {verdict.message}",
                verdict.status == "False",
                name,
            )


def _send(link: FenceLink, ops: list[Op]) -> None:
    for op in ops:
        if isinstance(op, Send):
            link.send_mission(*op.message)
        elif isinstance(op, Read):
            link.read_param(op.name)
        else:
            link.write_param(op.name, op.wire, int(op.ptype))


__all__ = [
    "FenceKeeper",
    "FenceLink",
    "Fences",
    "Op",
    "Phase",
    "Send",
    "Target",
    "Verdict",
    "stack_param_names",
    "target_of",
]
