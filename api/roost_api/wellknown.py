"""Well-known names Roost puts on Kubernetes objects: labels, annotations, taints, paths.

Everything that two components must spell the same way lives here, so the operator
that sets a label and the CLI or agent that reads it cannot drift apart.
"""

from __future__ import annotations

from roost_api.core import GROUP

PREFIX = f"{GROUP}/"

# Node labels (NFD-style: Roost owns the roost.dev/ prefix on nodes it manages).
LABEL_VEHICLE = f"{PREFIX}vehicle"
LABEL_VEHICLE_CLASS = f"{PREFIX}vehicle-class"
LABEL_VEHICLE_TYPE = f"{PREFIX}vehicle-type"
LABEL_SIMULATED = f"{PREFIX}simulated"
LABEL_STACK = f"{PREFIX}sitl-stack"

# Starling compatibility labels, set only when spec.starlingCompatibility is true.
STARLING_LABEL_TYPE = "starling.dev/type"
STARLING_LABEL_CLASS = "starling.dev/vehicle-class"
STARLING_LABEL_VEHICLE_TYPE = "starling.dev/vehicle-type"

# Node annotation listing every label/taint key Roost set; only these are ever removed.
ANNOTATION_MANAGED_LABELS = f"{PREFIX}managed-labels"
# A Vehicle's agent telemetry stream (ws://HOST:PORT/), read by `roost dashboard`.
ANNOTATION_TELEMETRY = f"{PREFIX}telemetry"
# The agent pod serving it (NAMESPACE/POD:PORT): the dashboard's way in through the
# API server's pod proxy. Both written by the agent itself.
ANNOTATION_TELEMETRY_POD = f"{PREFIX}telemetry-pod"

# A Vehicle's flight records server (http://HOST:PORT/) when the operator can reach it
# directly (the sandbox, where agents run as processes); otherwise the operator goes
# through the API server's pod proxy of the agent pod on the vehicle's node.
ANNOTATION_RECORDS = f"{PREFIX}records"

# Taint keeping ordinary workloads off vehicle nodes.
TAINT_VEHICLE = f"{PREFIX}vehicle"

# Labels on objects Roost creates (ConfigMaps, workloads, Jobs).
LABEL_MANAGED_BY = "app.kubernetes.io/managed-by"
MANAGED_BY = "roost"
LABEL_COMPONENT = f"{PREFIX}component"
LABEL_MISSION = f"{PREFIX}mission"

# Label the operator keeps on each RedundantAutopilot: the node of its Vehicle
# (Vehicle.spec.nodeName). An admission policy cannot look up the Vehicle, so the
# chart's node-restriction policy compares this label with the node name in the agent's
# service-account token; the agent also lists its RedundantAutopilots by this label.
# Only the operator writes it; the agent can write status only, never metadata. The same
# key annotates each component pod with the node it was made for.
LABEL_NODE = f"{PREFIX}node"

# Fleet guards on the cluster side of failover (re-pointing mavros, mission consequences,
# automatic failback); they never affect the on-vehicle switch, which is always allowed.
# "true" on a Vehicle pauses those actions for that vehicle.
ANNOTATION_PAUSE_FAILOVER_ACTIONS = f"{PREFIX}pause-failover-actions"
# After repeated failovers the operator latches a vehicle; a human clears the latch by
# setting this annotation to a new value (any token, e.g. a timestamp). The operator
# records the token it honoured in status, so one token clears one latch.
ANNOTATION_CLEAR_FAILOVER_LATCH = f"{PREFIX}clear-failover-latch"

# Annotation on component pods carrying a hash of the vehicle config, so edits replace them.
ANNOTATION_CONFIG_HASH = f"{PREFIX}config-hash"
# Annotation on each vehicle component Pod: a hash of the Pod as the operator built it
# (spec, labels, annotations); a different desired hash makes the operator replace it.
ANNOTATION_POD_HASH = f"{PREFIX}pod-hash"

# Where the per-vehicle config is mounted in every Roost-managed pod.
VEHICLE_CONFIG_FILE = "vehicle.config"
VEHICLE_CONFIG_MOUNTS = ("/etc/roost", "/etc/starling")

# Finalizer on Missions (kopf's), so deletion stops their work and releases claims first.
# Vehicles of earlier versions carry it too; kopf removes it, as no handler needs it.
FINALIZER = f"{PREFIX}cleanup"

# Each Vehicle's MAVLink signing key: Secret SIGNING_SECRET_PREFIX + vehicle (`roost keys`),
# handed by the vehicle's key pod to the agent on its node under SIGNING_HOST_DIR/<vehicle>.
SIGNING_SECRET_PREFIX = "roost-signing-"
SIGNING_HOST_DIR = "/var/lib/roost/signing"
