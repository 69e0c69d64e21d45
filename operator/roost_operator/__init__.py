"""Roost's Kubernetes operator (kopf): Vehicles, Missions and redundant autopilots.

Layout — thin kopf handlers over pure functions, one place per concept:

``main``
    kopf settings (finalizer/annotation prefixes under roost.dev, peering, posting
    level, timeouts), the startup hook, ``main()`` for the ``roost-operator`` script.
    Importing it registers every handler module listed in ``HANDLER_MODULES``.
``settings``
    Environment-driven settings (operator namespace, resync period, peering name).
``runtime``
    The :class:`~roost_operator.runtime.Runtime` (API client + settings) that startup
    stores in kopf's ``memo``; handlers get it with ``runtime(memo)``.
``kube``
    The only Kubernetes API access layer: get/list_objects/apply/merge_patch/delete/post_event
    on plain dicts. ``Kube.apply`` is server-side apply (field manager
    ``roost-operator``) that first compares and writes only on change; every write is
    counted. Resource kinds are declared there.
``vehicles/``
    ``config``: a vehicle's ``vehicle.config`` values, its ConfigMap, and
    ``mount_vehicle_config`` — the function every Roost pod on a vehicle goes through
    (component workloads here, onboard Mission pods too).
    ``placement``: node labels, the vehicle taint, the managed-labels annotation
    (NFD-style bookkeeping), node claims, and ``place_on_vehicle`` for pod specs.
    ``desired``: Vehicle (+ node, + RedundantAutopilot) → desired ConfigMap, component
    Deployments and SITL Deployments as plain dicts; status conditions and Ready.
    ``handlers``: the kopf handlers and the one level-based ``reconcile`` they call.

Further handler packages (``missions/``, ``autopilots/``) follow the same split:
``desired``/pure modules plus a thin ``handlers`` module added to ``HANDLER_MODULES``.
"""
