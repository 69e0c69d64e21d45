"""The operator's side of redundant-autopilot failover.

The node agent switches autopilots on its own and reports in the RedundantAutopilot's
status; this package turns those reports into the Vehicle's ``AgentConnected`` and
``AutopilotsHealthy`` conditions, re-points the vehicle's mavros at the new active
autopilot (also after an automatic failback, which the agent decides on the vehicle),
and applies the fleet guards (pause, latch, concurrency cap) to those cluster-side
actions — never to the on-vehicle switch.

``conditions``
    AgentConnected / AutopilotsHealthy from the agent's report (pure).
``guards``
    Fleet guards and the failover bookkeeping they need (pure); the mission state
    machine asks them too before applying ``spec.onFailover``.
``plan``
    One vehicle's cluster side of failover, as one pure decision.
``reconcile``
    One vehicle's run: fresh reads, :func:`plan.plan`, Events, the status write, the
    fleet-wide action ledger (no kopf).
``handlers``
    The kopf triggers (agent reports, silence, guard annotations, mavros rollout).
"""
