"""The operator's side of redundant-autopilot failover.

The node agent switches autopilots on its own and reports in the RedundantAutopilot's
status; this package turns those reports into the Vehicle's ``AgentConnected`` and
``AutopilotsHealthy`` conditions, re-points the vehicle's mavros at the new active
autopilot, issues automatic failback, and applies the fleet guards (pause, latch,
concurrency cap) to those cluster-side actions — never to the on-vehicle switch.

``conditions``
    AgentConnected / AutopilotsHealthy from the agent's report (pure).
``guards``
    Fleet guards and the failover bookkeeping they need (pure).
``plan``
    One vehicle's cluster side of failover, as one pure decision.
``handlers``
    The kopf handlers: fetch, call :func:`plan.plan`, write status, post Events.
"""
