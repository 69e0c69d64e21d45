"""The RedundantAutopilot resource: the autopilots of one vehicle and how to fail over.

Spec is written by people (and by the operator for manual requests); status is written
only by the node agent on the vehicle, because only it sees the MAVLink links. The
failover decision itself never waits for this object: the agent keeps the last spec on
disk and decides locally, then reports here.

Thresholds default to the starting points in the MAVLink health reference: message
silence WARN at 0.2 s and ERROR at 0.5 s (attitude streams at 50 Hz or more), heartbeat
WARN 1.5 s and ERROR 3 s, hysteresis clear time at least three times the confirm time.
"""

from __future__ import annotations

from datetime import datetime

from pydantic import Field
from pydantic.config import JsonDict

from roost_api import autopilot_enums, fence, shapes
from roost_api.core import DNS_LABEL_PATTERN, DNS_SUBDOMAIN_PATTERN, HealthLevel, Stack
from roost_api.meta import CONDITIONS_SCHEMA, ApiModel, Condition

# Defined in the pydantic-free roost_api.autopilot_enums (the node agent runs without
# pydantic).
HOST_PORT_PATTERN = autopilot_enums.HOST_PORT_PATTERN
MAVROS_HUB_BIND_PORT = autopilot_enums.MAVROS_HUB_BIND_PORT
MAX_AUTOPILOTS = autopilot_enums.MAX_AUTOPILOTS
AutopilotConditionReason = autopilot_enums.AutopilotConditionReason
AutopilotConditionType = autopilot_enums.AutopilotConditionType
AutopilotEntryConditionType = autopilot_enums.AutopilotEntryConditionType
CommandAction = autopilot_enums.CommandAction
CommandResultKind = autopilot_enums.CommandResultKind
DriftPolicy = autopilot_enums.DriftPolicy
Failback = autopilot_enums.Failback
FailoverMode = autopilot_enums.FailoverMode
FailoverTrigger = autopilot_enums.FailoverTrigger
FenceReason = autopilot_enums.FenceReason
FinalAction = autopilot_enums.FinalAction
HubScope = autopilot_enums.HubScope
HubSigning = autopilot_enums.HubSigning
HubTransport = autopilot_enums.HubTransport
LandedState = autopilot_enums.LandedState
ParametersReason = autopilot_enums.ParametersReason
SafetyRoutinePhase = autopilot_enums.SafetyRoutinePhase
StandbyInStepReason = autopilot_enums.StandbyInStepReason
hub_client_url = autopilot_enums.hub_client_url


class AutopilotSpec(ApiModel):
    """One flight controller of the vehicle."""

    name: str = Field(
        min_length=1,
        max_length=shapes.AUTOPILOT_NAME_MAX,
        pattern=DNS_LABEL_PATTERN,
        description="Unique name, at most 58 characters: a simulated vehicle runs it as "
        "container and component sitl-<name>.",
    )
    stack: Stack = Field(description="Flight stack: px4 or ardupilot.")
    connection: str = Field(
        max_length=shapes.URL_MAX,
        description="How the agent reaches it: serial:///dev/DEVICE:BAUD (e.g. "
        "serial:///dev/ttyUSB0:921600), udp://HOST:PORT or udpin://HOST:PORT (the agent "
        "listens), udpout://HOST:PORT (the agent sends), tcp://HOST:PORT (connects) or "
        "tcpin://HOST:PORT (accepts); HOST is an IPv4 address or a host name, PORT 1-65535.",
        json_schema_extra=shapes.validations(shapes.CONNECTION_RULES),
    )
    fcu_url: str | None = Field(
        default=None,
        max_length=shapes.URL_MAX,
        description="URL mavros uses for this autopilot when it is active; defaults to the "
        "connection. A serial port cannot be opened twice, so on hardware route it through "
        "a MAVLink router and give the router's UDP endpoint here.",
        json_schema_extra=shapes.validations(shapes.FCU_URL_RULES),
    )
    sysid: int = Field(ge=1, le=255, description="MAVLink system id; unique per vehicle.")
    component_id: int = Field(
        default=1, ge=1, le=255, description="MAVLink component id of the autopilot."
    )
    bridge_channel: int = Field(
        ge=0,
        le=63,
        description="Bridge input (GPIO line offset) that connects this autopilot to the motors.",
    )


class Thresholds(ApiModel):
    """Health thresholds; see the MAVLink health reference for their origin."""

    # Defaults: a PX4 or ArduPilot link streams ATTITUDE at 50 Hz (roost_agent.streams), so
    # 200 ms of silence is 10 missed samples. The silence threshold is learnt per autopilot
    # from the gaps between its messages (roost_agent.health: the worst gap of the last
    # seconds times silenceMargin) and kept between messageErrorMinMs and messageErrorMs;
    # the ceiling also applies while it learns (after start-up, a reboot, a stream-rate
    # request). The floor of 60 ms comes from the recordings (docs/health-model.md): PX4's
    # worst healthy gap is 9-12 ms (2.5 x 12 = 30 ms, held at 60), ArduCopter's ~25 ms
    # (~63 ms); 50 ms of jitter lifts it to ~125 ms, a 10 Hz link to the ceiling.
    # messageErrorMinMs = messageErrorMs gives back a fixed threshold.
    message_warn_ms: int = Field(
        default=100,
        ge=10,
        le=60000,
        description="Any-message age WARN at the ceiling; scaled with the learnt threshold.",
    )
    message_error_ms: int = Field(
        default=200,
        ge=20,
        le=60000,
        description="Any-message age ERROR (silent link): the learnt threshold's ceiling.",
    )
    message_error_min_ms: int = Field(
        default=60,
        ge=10,
        le=60000,
        description="Floor of the learnt silence threshold (above messageErrorMs: no effect).",
    )
    silence_margin: float = Field(
        default=2.5,
        ge=1.0,
        le=20.0,
        description="Silence ERROR after this many times the worst recent gap between messages.",
    )
    # HEARTBEAT is 1 Hz on both stacks. Each threshold sits half a period between two
    # counts of consecutive lost heartbeats (plus jitter), so WARN takes two in a row and
    # ERROR four; at 5 % loss that is an ERROR once in ~47 hours per link, where 3000 ms
    # (two lost plus jitter) gave several an hour. The arithmetic: docs/health-model.md.
    heartbeat_warn_ms: int = Field(
        default=2500,
        ge=100,
        le=60000,
        description="Heartbeat age WARN (default: two 1 Hz heartbeats lost in a row).",
    )
    heartbeat_error_ms: int = Field(
        default=4500,
        ge=200,
        le=60000,
        description="Heartbeat age ERROR (default: four 1 Hz heartbeats lost in a row).",
    )
    confirm_ms: int = Field(
        default=20,
        ge=0,
        le=10000,
        description="A failing signal must persist this long before it counts (T_on).",
    )
    clear_ms: int = Field(
        default=1000,
        ge=0,
        le=60000,
        description="A cleared signal must stay clear this long to count healthy (T_off).",
    )
    sensor_persist_ms: int = Field(
        default=600,
        ge=0,
        le=10000,
        description="A critical sensor bit must stay unhealthy this long (3 samples at 5 Hz).",
    )
    max_tilt_deg: float = Field(
        default=60.0, gt=0, le=180, description="Attitude beyond this is ERROR."
    )


class SafetyRoutine(ApiModel):
    """What the new active autopilot does right after a failover."""

    hold_seconds: float = Field(
        default=3.0, ge=0, le=120, description="Seconds to hold position before the final action."
    )
    final_action: FinalAction = Field(
        default=FinalAction.LAND, description="Land, ReturnToLaunch or Hold after holding."
    )
    skip_in_manual_mode: bool = Field(
        default=True,
        description="When a pilot flies in a manual mode, switch but leave control to them.",
    )


class StandbyLimits(ApiModel):
    """How far a standby may differ from the active autopilot and still count as in step."""

    position_m: float = Field(
        default=3.0,
        gt=0,
        le=10000,
        description="Largest horizontal distance (m) between the standby's and the active "
        "autopilot's position estimate.",
    )
    altitude_m: float = Field(
        default=1.5,
        gt=0,
        le=10000,
        description="Largest difference (m) between their altitudes above home.",
    )
    confirm_ms: int = Field(
        default=1000,
        ge=0,
        le=60000,
        description="How long a difference must last before the standby counts as out of "
        "step (mirrored commands reach the autopilots a few milliseconds apart).",
    )


class HubEndpoint(ApiModel):
    """One more endpoint of the hub, with its own scope and signing (a ground station's).

    The hub's ``udp`` and ``tcp`` endpoints let clients send everything; an endpoint
    here says what its clients may send and whether they must sign.
    """

    name: str = Field(
        max_length=32,
        pattern=DNS_LABEL_PATTERN,
        description="Names the endpoint in the status, metrics and Events (e.g. gcs).",
    )
    transport: HubTransport = Field(
        default=HubTransport.UDP, description="UDP (clients are the addresses heard) or TCP."
    )
    address: str = Field(
        max_length=shapes.URL_MAX,
        pattern=HOST_PORT_PATTERN,
        description="HOST:PORT the agent listens on.",
    )
    scope: HubScope = Field(
        default=HubScope.EVERYTHING,
        description="What clients may send: Everything; ReadOnly (parameter, mission and "
        "message reads); AllowList (allowMessages, and allowCommands inside COMMAND_LONG "
        "and COMMAND_INT). Anything else is dropped and counted.",
    )
    allow_messages: list[int] = Field(
        default_factory=list,
        max_length=256,
        description="MAVLink message ids clients may send (scope AllowList).",
        json_schema_extra={"items": {"type": "integer", "minimum": 0, "maximum": 16777215}},
    )
    allow_commands: list[int] = Field(
        default_factory=list,
        max_length=256,
        description="MAV_CMD ids clients may send in COMMAND_LONG/COMMAND_INT (scope AllowList).",
        json_schema_extra={"items": {"type": "integer", "minimum": 0, "maximum": 65535}},
    )
    signing: HubSigning = Field(
        default=HubSigning.AUTO,
        description="Auto: clients must sign with the vehicle's key unless the address is "
        "loopback (without a key the agent refuses the endpoint); Required: also on "
        "loopback; Unauthenticated: never (anyone who reaches the address may send what "
        "the scope allows; the status says so).",
    )


class HubSpec(ApiModel):
    """The vehicle's MAVLink endpoint(s), served by the node agent (the MAVLink hub).

    Clients (mavros, MAVSDK, MAVProxy, a ground station) connect here instead of to an
    autopilot; the agent routes them to the active autopilot and keeps them connected
    across a failover.
    """

    sysid: int | None = Field(
        default=None,
        ge=1,
        le=255,
        description="The vehicle's MAVLink system id as clients see it (normally the "
        "Vehicle's sysid); defaults to the primary autopilot's sysid.",
    )
    udp: str = Field(
        default="127.0.0.1:14550",
        max_length=shapes.URL_MAX,
        pattern=HOST_PORT_PATTERN,
        description="HOST:PORT the agent listens on for UDP clients (mavros).",
    )
    tcp: str | None = Field(
        default=None,
        max_length=shapes.URL_MAX,
        pattern=HOST_PORT_PATTERN,
        description="HOST:PORT the agent accepts TCP clients on (a ground station); none "
        "when unset.",
    )
    mirror: bool = Field(
        default=True,
        description="Mirror what clients send that changes flight state (arm, mode, "
        "takeoff/land/RTL, mission items, setpoints) to every standby.",
    )
    standby_limits: StandbyLimits = Field(
        default_factory=StandbyLimits,
        description="When a standby counts as in step with the active autopilot.",
    )
    endpoints: list[HubEndpoint] = Field(
        default_factory=list,
        max_length=8,
        description="Further endpoints, each with its own scope and signing (a ground "
        "station on the network: signed, read-only or an allow-list).",
    )


PARAMETER_NAME_PATTERN = r"^[A-Za-z0-9_]{1,16}$"
MAX_PARAMETERS = 512


class ParameterValue(ApiModel):
    """One autopilot parameter and the value it must hold."""

    name: str = Field(
        max_length=16,
        pattern=PARAMETER_NAME_PATTERN,
        description="The firmware's parameter name (at most 16 characters, as MAVLink's "
        "param_id), e.g. MIS_TAKEOFF_ALT on PX4, PILOT_TKOFF_ALT on ArduPilot.",
    )
    value: float = Field(
        description="The value in the parameter's own unit; an integer parameter takes a "
        "whole number within its type's range."
    )


_BY_NAME: JsonDict = {"x-kubernetes-list-type": "map", "x-kubernetes-list-map-keys": ["name"]}


class ParametersSpec(ApiModel):
    """Autopilot parameters as declared state, per flight stack (names and units differ
    between PX4 and ArduPilot). The agent writes them to every autopilot of that stack,
    reads them back and keeps watching them."""

    px4: list[ParameterValue] = Field(
        default_factory=list,
        max_length=MAX_PARAMETERS,
        description="Parameters of every PX4 autopilot of the vehicle.",
        json_schema_extra=_BY_NAME,
    )
    ardupilot: list[ParameterValue] = Field(
        default_factory=list,
        max_length=MAX_PARAMETERS,
        description="Parameters of every ArduPilot autopilot of the vehicle.",
        json_schema_extra=_BY_NAME,
    )
    on_drift: DriftPolicy = Field(
        default=DriftPolicy.REPORT,
        description="A parameter changed on an autopilot by someone else after the agent "
        "set it: Report (the ParametersInSync condition names it) or Restore (written back "
        "too). Never written while the vehicle is armed.",
    )


VERSION_PATTERN = r"^[0-9]{1,3}\.[0-9]{1,3}\.[0-9]{1,3}$"


class FirmwareRequirement(ApiModel):
    """What firmware the autopilots must run (checked by the agent from each one's
    AUTOPILOT_VERSION; a Mission's preflight refuses a vehicle that breaks it)."""

    px4_minimum: str | None = Field(
        default=None,
        max_length=11,
        pattern=VERSION_PATTERN,
        description="Lowest PX4 version every PX4 autopilot must run, MAJOR.MINOR.PATCH.",
    )
    ardupilot_minimum: str | None = Field(
        default=None,
        max_length=11,
        pattern=VERSION_PATTERN,
        description="Lowest ArduPilot version every ArduPilot autopilot must run.",
    )
    identical: bool = Field(
        default=False,
        description="Every autopilot of a stack runs the same version and build (the git "
        "hash in AUTOPILOT_VERSION): a standby flies as the active would.",
    )


class FencePoint(ApiModel):
    """One point of a fence, in degrees (WGS84)."""

    latitude: float = Field(ge=-90, le=90, description="Latitude in degrees.")
    longitude: float = Field(ge=-180, le=180, description="Longitude in degrees.")


class FenceCircle(ApiModel):
    """A circular inclusion area."""

    latitude: float = Field(ge=-90, le=90, description="Centre latitude in degrees.")
    longitude: float = Field(ge=-180, le=180, description="Centre longitude in degrees.")
    radius_m: float = Field(gt=0, le=100000, description="Radius in metres.")


class Fence(ApiModel):
    """A flying area: an inclusion polygon or circle, a maximum altitude above home and
    what the autopilot does on a breach (docs/missions.md, "Geofence")."""

    polygon: list[FencePoint] = Field(
        default_factory=list,
        max_length=fence.MAX_VERTICES,
        description="Inclusion polygon, at least three vertices, closed implicitly (last "
        "to first); its edges must not cross. Exactly one of polygon and circle.",
    )
    circle: FenceCircle | None = Field(
        default=None, description="Inclusion circle. Exactly one of polygon and circle."
    )
    max_altitude_m: float = Field(
        gt=0, le=10000, description="Maximum altitude above home in metres."
    )
    action: fence.FenceAction = Field(
        default=fence.FenceAction.RETURN,
        description="On a breach: Hold (hover where it is), Return (to launch), Land, or "
        "Report (tell the ground station only).",
    )


FENCE_RULES: list[JsonDict] = [
    {
        "rule": "(has(self.circle) ? 1 : 0) + (has(self.polygon) && size(self.polygon) > 0 "
        "? 1 : 0) == 1",
        "message": "a fence has exactly one of polygon and circle",
    },
    {
        "rule": "!has(self.polygon) || size(self.polygon) == 0 || size(self.polygon) >= 3",
        "message": "an open polygon: a fence polygon needs at least three vertices",
    },
]


class AssignedFence(ApiModel):
    """The fence a Mission asks this vehicle's autopilots to hold (written by the
    operator during the Mission's preflight, removed when the Mission lets the vehicle
    go; the agent then restores the fence the autopilots held before)."""

    mission: str = Field(max_length=317, description="The Mission, as namespace/name.")
    id: str = Field(max_length=64, description="Id of the fence's content.")
    fence: Fence = Field(
        description="The fence.", json_schema_extra={"x-kubernetes-validations": list(FENCE_RULES)}
    )


class FailoverPolicy(ApiModel):
    """How the agent decides and what it does after deciding."""

    mode: FailoverMode = Field(
        default=FailoverMode.AUTOMATIC,
        description="Automatic: the agent switches on its own. Manual: only on request.",
    )
    thresholds: Thresholds = Field(default_factory=Thresholds, description="Health thresholds.")
    safety_routine: SafetyRoutine = Field(
        default_factory=SafetyRoutine, description="Routine run on the new active autopilot."
    )
    failback: Failback = Field(
        default=Failback.MANUAL,
        description="Never, Manual (a Switch command), or OnGround (back to the primary once "
        "landed and healthy). Never automatic in the air.",
    )


class AutopilotCommand(ApiModel):
    """A request to the node agent; executed at most once, identified by ``id``."""

    id: str = Field(
        min_length=1,
        max_length=shapes.COMMAND_ID_MAX,
        pattern=shapes.COMMAND_ID_PATTERN,
        description="Unique id of this request: letters, digits, '-', '_', '.' or ':'.",
    )
    action: CommandAction = Field(
        description="Switch, SafetyRoutine, EmergencyStop (force disarm) or ClearLatch."
    )
    target: str | None = Field(
        default=None,
        max_length=shapes.AUTOPILOT_NAME_MAX,
        description="Autopilot to switch to (Switch only).",
    )
    issued_at: datetime = Field(description="When the request was made.")
    deadline_seconds: int = Field(
        default=10,
        ge=1,
        le=3600,
        description="The agent ignores the request when it sees it later than this after "
        "issuedAt (stale after a partition).",
    )


class RedundantAutopilotSpec(ApiModel):
    """Desired state of a RedundantAutopilot."""

    vehicle_name: str = Field(
        min_length=1,
        max_length=shapes.VEHICLE_NAME_MAX,
        pattern=DNS_SUBDOMAIN_PATTERN,
        description="The Vehicle these autopilots fly; the RedundantAutopilot has the same "
        "name, so a vehicle has exactly one. Immutable.",
        json_schema_extra={
            "x-kubernetes-validations": [
                {"rule": "self == oldSelf", "message": "vehicleName is immutable"}
            ]
        },
    )
    autopilots: list[AutopilotSpec] = Field(
        min_length=2,
        max_length=MAX_AUTOPILOTS,
        description="The vehicle's flight controllers (two or more).",
    )
    primary: str = Field(
        max_length=shapes.AUTOPILOT_NAME_MAX,
        description="Name of the autopilot that flies when all are healthy.",
    )
    failover_policy: FailoverPolicy = Field(
        default_factory=FailoverPolicy, description="How and when to fail over."
    )
    command: AutopilotCommand | None = Field(
        default=None, description="Latest request to the agent; see status.lastCommand."
    )
    hub: HubSpec | None = Field(
        default=None,
        description="Serve the vehicle's MAVLink endpoint from the agent, routed to the "
        "active autopilot (clients then never reconnect on a failover).",
    )
    firmware: FirmwareRequirement | None = Field(
        default=None,
        description="Firmware the autopilots must run (reported as the FirmwareAcceptable "
        "condition).",
    )
    parameters: ParametersSpec | None = Field(
        default=None,
        description="Autopilot parameters the agent keeps on every autopilot of the "
        "vehicle (written while disarmed, read back, watched for drift).",
    )
    fence: AssignedFence | None = Field(
        default=None,
        description="Written by the operator: the geofence of the Mission that holds this "
        "vehicle. The agent uploads it to every autopilot (mission protocol and the stack's "
        "fence parameters), reads it back, and restores the previous fence once it goes.",
    )


# On the whole object: metadata.name is only visible to CEL from the root.
REDUNDANT_AUTOPILOT_ROOT_RULES = [
    shapes.rule(
        "self.metadata.name == self.spec.vehicleName",
        "metadata.name must equal spec.vehicleName: a vehicle has one RedundantAutopilot, "
        "named after it",
    )
]

REDUNDANT_AUTOPILOT_RULES = [
    {
        "rule": "self.autopilots.all(a, self.autopilots.exists_one(b, b.name == a.name))",
        "message": "autopilot names must be unique",
    },
    {
        "rule": "self.autopilots.all(a, self.autopilots.exists_one(b, b.sysid == a.sysid))",
        "message": "autopilot sysids must be unique: two autopilots with one sysid are merged "
        "on a MAVLink link and commands reach both",
    },
    {
        "rule": "self.autopilots.all(a, self.autopilots.exists_one(b, "
        "b.bridgeChannel == a.bridgeChannel))",
        "message": "autopilot bridgeChannels must be unique",
    },
    {
        "rule": "self.autopilots.exists(a, a.name == self.primary)",
        "message": "primary must be the name of one of the autopilots",
    },
    {
        "rule": "!has(self.command) || self.command.action != 'Switch' || "
        "(has(self.command.target) && self.autopilots.exists(a, a.name == self.command.target))",
        "message": "a Switch command needs a target that is one of the autopilots",
    },
    {
        # Absent objects are not defaulted by the API server (only their fields are, once
        # present), so guard with has(): absent thresholds mean the valid defaults.
        "rule": "!has(self.failoverPolicy) || !has(self.failoverPolicy.thresholds) || "
        "(self.failoverPolicy.thresholds.messageWarnMs < "
        "self.failoverPolicy.thresholds.messageErrorMs && "
        "self.failoverPolicy.thresholds.heartbeatWarnMs < "
        "self.failoverPolicy.thresholds.heartbeatErrorMs)",
        "message": "warn thresholds must be below error thresholds",
    },
    {
        "rule": "!has(self.parameters) || !has(self.parameters.px4) || "
        "size(self.parameters.px4) == 0 || self.autopilots.exists(a, a.stack == 'px4')",
        "message": "parameters.px4 declared but no autopilot runs PX4",
    },
    {
        "rule": "!has(self.parameters) || !has(self.parameters.ardupilot) || "
        "size(self.parameters.ardupilot) == 0 || "
        "self.autopilots.exists(a, a.stack == 'ardupilot')",
        "message": "parameters.ardupilot declared but no autopilot runs ArduPilot",
    },
]


class FirmwareInfo(ApiModel):
    """What one autopilot's AUTOPILOT_VERSION says about its firmware and board."""

    version: str = Field(max_length=11, description="Flight software version MAJOR.MINOR.PATCH.")
    version_type: str = Field(
        max_length=16, description="dev, alpha, beta, rc or official (FIRMWARE_VERSION_TYPE)."
    )
    git_hash: str = Field(default="", max_length=16, description="The build's git hash (8 bytes).")
    board_version: int = Field(default=0, description="Board (hardware) version.")
    vendor_id: int = Field(default=0, description="USB vendor id of the board (0: unknown).")
    product_id: int = Field(default=0, description="USB product id of the board (0: unknown).")
    capabilities: list[str] = Field(
        default_factory=list,
        max_length=64,
        description="MAV_PROTOCOL_CAPABILITY flags the firmware announces.",
    )


class AutopilotHealth(ApiModel):
    """One autopilot's health as the agent last judged it."""

    name: str = Field(max_length=63, description="Autopilot name.")
    level: HealthLevel = Field(
        description="OK, WARN, STARTING (booting, estimator or GPS start-up), ERROR or STALE "
        "(no data)."
    )
    reasons: list[str] = Field(default_factory=list, description="Why it is not OK.")
    heartbeat_age_ms: int | None = Field(default=None, description="Age of the last heartbeat.")
    message_age_ms: int | None = Field(default=None, description="Age of the last message.")
    mode: str | None = Field(default=None, description="Flight mode from the heartbeat.")
    armed: bool | None = Field(default=None, description="Armed flag from the heartbeat.")
    landed_state: LandedState | None = Field(
        default=None, description="OnGround, InAir, Takeoff or Landing (EXTENDED_SYS_STATE)."
    )
    system_status: str | None = Field(default=None, description="MAV_STATE from the heartbeat.")
    unhealthy_sensors: list[str] = Field(
        default_factory=list, description="Enabled SYS_STATUS sensors reported unhealthy."
    )
    firmware: FirmwareInfo | None = Field(
        default=None, description="Firmware and board, from AUTOPILOT_VERSION."
    )
    conditions: list[Condition] = Field(
        default_factory=list,
        description="Per-autopilot conditions: StandbyInStep (with the hub: whether this "
        "standby follows the active autopilot's armed state, mode and position); "
        "ParametersInSync (with spec.parameters: whether it holds them, naming any that "
        "differ with both values).",
        json_schema_extra=CONDITIONS_SCHEMA,
    )


class FailoverRecord(ApiModel):
    """The most recent switch of the active autopilot."""

    time: datetime = Field(description="When the bridge switched.")
    from_autopilot: str = Field(alias="from", description="Autopilot that was active.")
    to_autopilot: str = Field(alias="to", description="Autopilot that became active.")
    reason: str = Field(description="Why, e.g. heartbeat lost on fc1.")
    latency_ms: float = Field(description="Detection to bridge switched, measured on-vehicle.")
    trigger: FailoverTrigger = Field(description="Automatic, Command or Failback.")
    safety_routine: SafetyRoutinePhase | None = Field(
        default=None,
        description="The safety routine after the switch: its plan (Run, or Skipped when a "
        "pilot flies manually) then its progress (Holding, Landing, Landed, Held…).",
    )
    standby_in_step: bool | None = Field(
        default=None,
        description="Whether the autopilot switched to was in step with the one it replaced "
        "(None: not known, e.g. without the hub).",
    )


class CommandResult(ApiModel):
    """The last command the agent processed."""

    id: str = Field(description="The command's id.")
    result: CommandResultKind = Field(description="Executed, Rejected or Expired.")
    message: str = Field(default="", description="Details.")
    time: datetime = Field(description="When the agent processed it.")


class HubEndpointStatus(ApiModel):
    """One endpoint of the vehicle's hub as the agent serves it."""

    name: str = Field(description="The endpoint (udp and tcp: the hub's own).")
    transport: HubTransport = Field(description="UDP or TCP.")
    address: str = Field(description="HOST:PORT it listens on.")
    scope: HubScope = Field(description="What its clients may send.")
    signed: bool = Field(
        description="Whether clients must sign; false beyond loopback only when the spec "
        "says Unauthenticated."
    )
    dropped: int = Field(
        default=0,
        description="Client frames dropped since the agent started (unsigned, badly "
        "signed, replayed or outside the scope).",
    )


class RedundantAutopilotStatus(ApiModel):
    """Observed state of a RedundantAutopilot, written by the node agent."""

    observed_generation: int | None = Field(
        default=None, description="metadata.generation the agent last applied."
    )
    conditions: list[Condition] = Field(
        default_factory=list,
        json_schema_extra=CONDITIONS_SCHEMA,
        description="Ready, ActiveHealthy, Redundant, FailedOver; FirmwareAcceptable with "
        "spec.firmware.",
    )
    active_autopilot: str | None = Field(
        default=None, description="Autopilot currently connected to the motors."
    )
    autopilots: list[AutopilotHealth] = Field(
        default_factory=list, description="Health of each autopilot."
    )
    last_failover: FailoverRecord | None = Field(
        default=None, description="The most recent switch."
    )
    failover_count: int = Field(default=0, description="Switches since the agent started.")
    latched: bool = Field(
        default=False,
        description="A failover happened this flight; no automatic switch back until cleared.",
    )
    last_command: CommandResult | None = Field(
        default=None, description="The last command the agent processed."
    )
    hub_endpoints: list[HubEndpointStatus] = Field(
        default_factory=list,
        description="The vehicle's MAVLink endpoints: scope, signing, frames dropped.",
    )
    node_name: str | None = Field(default=None, description="Node of the reporting agent.")
    reported_at: datetime | None = Field(
        default=None, description="When the agent last reported (refreshed periodically)."
    )
