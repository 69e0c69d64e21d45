"""The Vehicle controller: a Vehicle turns a node into a drone of the fleet.

``config``, ``placement``, ``desired``
    Pure desired state: the vehicle's config values and ConfigMap, node labels and
    taint, component and SITL Pods (and when to replace them), conditions and Ready.
``plan``
    The whole decision about one Vehicle (failover side included), pure.
``controller``
    Observe → plan → apply → one status write, one lock per vehicle (no kopf).
``status``
    The status patch (only changed fields, with the resourceVersion read).
``handlers``
    The kopf triggers and their registration.
"""
