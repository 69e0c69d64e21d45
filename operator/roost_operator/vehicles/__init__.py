"""The Vehicle controller: a Vehicle turns a node into a drone of the fleet.

One reconcile follows a Vehicle's name through these modules, each once:

``controller``
    The reconcile: one lock per vehicle, conflict retries, the fleet's action ledger;
    observe → plan → apply → status (no kopf).
``observe``
    Everything the decision reads, the live component Pods and the clock included.
``plan``
    The whole decision about one Vehicle (failover side included), pure.
``apply``
    The plan's writes, and what the API server answered; the release of a gone Vehicle.
``status``
    The status from the plan and that answer, written once (only changed fields, with
    the resourceVersion read), and its Events.

Pure building blocks the plan and the status use: ``config`` (config values and
ConfigMap), ``placement`` (node labels, taint, reachability), ``manifests`` (autopilots,
workloads, component Pods), ``pods`` (the step for a live Pod, its readiness),
``conditions`` (NodeBound, ComponentsReady, Ready), ``flight`` (nothing changes in the
air). ``handlers`` and ``watched`` are the kopf triggers and the watches that queue
names.
"""
