"""Roost's Kubernetes operator (kopf): Vehicles, Missions and redundant autopilots.

Layout — one controller per resource, each the only writer of its status (the node
agent is the only writer of RedundantAutopilot status); thin kopf handlers over pure
decisions:

``main``
    kopf settings, the registry every controller registers its handlers in, ``main()``
    for the ``roost-operator`` script. Nothing registers on import.
``settings``
    Every setting, documented per field, built once from the environment and flags and
    passed to kopf in the memo.
``runtime``
    What startup adds to the memo: the API client (:mod:`roost_kube`), the settings and
    the controllers with per-process state.
``edge``
    The Kubernetes layer's temporary/permanent errors mapped to kopf's, naming the object.
``claims``
    A Mission's claim on a Vehicle: one Lease per claimed vehicle (pure).
``vehicles/``
    The Vehicle controller: desired state (``config``, ``placement``, ``desired``), the
    whole decision (``plan``, failover side included), observe → plan → apply → status
    (``controller``), kopf triggers (``handlers``).
``autopilots/``
    Pure failover decisions the Vehicle controller applies: conditions, fleet guards,
    the failover plan (which autopilot the workloads follow).
``missions/``
    The Mission controller: selection, preflight, workloads, the state machine (pure),
    ``cluster`` (reads, claims, writes) and ``handlers``.
"""
