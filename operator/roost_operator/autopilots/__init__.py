"""The operator's side of redundant-autopilot failover, as pure decisions.

The node agent switches autopilots on its own and reports in the RedundantAutopilot's
status (it is that status's only writer); this package decides what those reports mean
for the Vehicle: its ``AgentConnected`` and ``AutopilotsHealthy`` conditions, which
autopilot the vehicle's mavros follows (also after an automatic failback, which the
agent decides on the vehicle), and the fleet guards (pause, latch, concurrency cap) on
those cluster-side actions — never on the on-vehicle switch. The Vehicle controller's
plan (:mod:`roost_operator.vehicles.plan`) calls it with what it observed (the URL mavros
uses for each autopilot among it); this package imports nothing of the Vehicle
controller.

``conditions``
    AgentConnected / AutopilotsHealthy from the agent's report (pure).
``guards``
    Fleet guards and the failover bookkeeping they need (pure); the mission state
    machine asks them too before applying ``spec.onFailover``.
``plan``
    One vehicle's cluster side of failover, as one pure decision.
"""
