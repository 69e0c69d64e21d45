"""The Mission controller: claim vehicles, gate on preflight, run workloads, abort.

Split like the vehicle controller — pure decisions, thin I/O, thin kopf handlers:

``selection``
    Which vehicles a mission may use (label selector and/or names), which of them are
    free, and the all-or-nothing claim decision.
``preflight``
    Per-vehicle checks before anything starts (Ready, agent connected, active autopilot
    healthy, redundancy).
``workloads``
    Job names and manifests for the onboard (one per vehicle) and offboard workloads,
    and what a Job's status means for the mission.
``machine``
    The phase state machine: one :class:`~roost_operator.missions.machine.Observation`
    in, one :class:`~roost_operator.missions.machine.Plan` out (claims, releases, Jobs
    to create/delete, autopilot commands, the new status and its Events).
``cluster``
    Reads an Observation from the API and carries out a Plan (claims use optimistic
    concurrency on Vehicle status).
``interest``
    Which Missions an event on a Vehicle, claim or RedundantAutopilot concerns, and
    when a Mission is looked at again without an event.
``controller``
    One queued Mission key, one reconcile on the engine's work queue
    (:mod:`roost_operator.engine`); the deletion after any running reconcile.
``handlers``
    kopf: event handlers that queue Mission keys (Mission, Vehicle,
    RedundantAutopilot, Job events), and a deletion handler that releases the vehicles.
"""
