"""Wake-ups between the mission controller's handlers (roost_operator.missions.wakeups):
real asyncio tasks on one event loop, no cluster."""

from __future__ import annotations

import asyncio

from roost_operator.missions.wakeups import Wakeups, sleep_until_woken


def test_wakeups_reach_the_holder_the_claimant_and_waiting_missions() -> None:
    async def scenario() -> list[bool]:
        wakeups = Wakeups()
        holder, waiting, other = (
            wakeups.register(k) for k in ("ns/holder", "ns/waiting", "ns/other")
        )
        wakeups.track("ns/holder", vehicles=["a"], waiting=False)
        wakeups.track("ns/waiting", vehicles=[], waiting=True)
        wakeups.track("ns/other", vehicles=["b"], waiting=False)
        wakeups.wake_holder("a")
        seen = [holder.is_set(), waiting.is_set(), other.is_set()]
        holder.clear()
        wakeups.wake_for_vehicle("c", claimant="ns/other")
        seen += [holder.is_set(), waiting.is_set(), other.is_set()]
        never = asyncio.Event()
        woken = await sleep_until_woken(holder, never.wait(), 0.01)
        return [*seen, woken]

    assert asyncio.run(scenario()) == [True, False, False, False, True, True, False]
