"""The shapes and bounds of every user string Roost writes somewhere else.

Rule: whatever Roost will write somewhere, it validates at the door for that place. A
Vehicle name that fits a CRD but not a label value would otherwise be accepted, then fail
in the operator on every retry; so each bound here is derived from where the string ends
up, and the CRDs (through the models) carry it as a length, a pattern or a CEL rule whose
message names the field and the rule.

Where user strings end up:

======================  ==============================================================
string                  written as
======================  ==============================================================
Vehicle name            node label value ``roost.dev/vehicle``, taint value, the labels
                        of its workloads and ConfigMaps: a label value, 63 characters
spec.nodeName           label ``roost.dev/node`` on the vehicle's RedundantAutopilot: 63
autopilot name          container name and label value ``sitl-<name>`` of a simulated
                        vehicle's SITL Deployment ``<vehicle>-sitl-<name>``: 63 - 5 = 58
Mission name            Event names ``<name>.<hash>``, Job names and the
                        ``roost.dev/mission`` label: 63, like the Jobs named after it
config key              environment variable and ConfigMap key: ``[A-Z_][A-Z0-9_]*``
config value            one ``KEY=VALUE`` line of ``vehicle.config``: no line breaks or
                        other control characters (refused, not escaped: a reader of the
                        file sees exactly the value the user wrote)
whole spec.config       two annotations Roost's writes carry (see below)
connection, fcuUrl      sockets and serial ports the agent opens, mavros' FCU URL
image                   a container image: non-empty, no whitespace
selector keys/values    label keys and values (a selector with an invalid one can never
                        match; the API server rejects it when Roost lists Vehicles)
======================  ==============================================================

Config size: ``kubectl apply`` keeps the whole manifest in
``kubectl.kubernetes.io/last-applied-configuration``, and Vehicles handled by operators
before ``roost_operator.main.NoDiffBase`` still carry kopf's copy of the last handled
spec as JSON in ``roost.dev/last-handled-configuration``; all annotations of an object
share 256 KiB (262144 bytes). kopf's JSON escapes non-ASCII, so one character of a
value can take up to 12 bytes there (a surrogate pair ``\\ud83d\\ude00``) and 6 in
kubectl's copy (``\\u003c``). With :data:`CONFIG_TOTAL_MAX` characters of keys and values
(and at most :data:`CONFIG_MAX_ENTRIES` entries, 6 bytes of JSON punctuation each) the two
copies take at most ``8192 * 18 + 64 * 6 * 2 = 148224`` bytes (145 KiB), which leaves over
110 KiB for the rest of the spec and for the user's own annotations.
``tests/unit/test_api_shapes.py`` builds that worst case and measures it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, cast

from pydantic.config import JsonDict, JsonValue

LABEL_VALUE_MAX: Final = 63
VEHICLE_NAME_MAX: Final = LABEL_VALUE_MAX
NODE_NAME_MAX: Final = LABEL_VALUE_MAX
SITL_COMPONENT_PREFIX: Final = "sitl-"
AUTOPILOT_NAME_MAX: Final = LABEL_VALUE_MAX - len(SITL_COMPONENT_PREFIX)
MISSION_NAME_MAX: Final = LABEL_VALUE_MAX

CONFIG_MAX_ENTRIES: Final = 64
CONFIG_KEY_MAX: Final = 128
CONFIG_VALUE_MAX: Final = 4096
CONFIG_TOTAL_MAX: Final = 8192
ANNOTATIONS_TOTAL_MAX: Final = 256 * 1024
KOPF_BYTES_PER_CHAR: Final = 12
KUBECTL_BYTES_PER_CHAR: Final = 6
JSON_BYTES_PER_ENTRY: Final = 6  # "K":"V", around each entry

IMAGE_MAX: Final = 512
URL_MAX: Final = 256
COMMAND_ID_MAX: Final = 64

# -- names ---------------------------------------------------------------------------

DNS_LABEL: Final = r"[a-z0-9]([-a-z0-9]*[a-z0-9])?"
DNS_SUBDOMAIN: Final = rf"{DNS_LABEL}(\.{DNS_LABEL})*"
LABEL_NAME: Final = r"[A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?"
LABEL_VALUE_PATTERN: Final = r"^(([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9])?$"
LABEL_KEY_PATTERN: Final = rf"^({DNS_SUBDOMAIN}/)?{LABEL_NAME}$"
LABEL_KEY_PREFIX_PATTERN: Final = r"^([^/]{1,253}/)?[^/]+$"
CONFIG_KEY_PATTERN: Final = r"^[A-Z_][A-Z0-9_]*$"
IMAGE_PATTERN: Final = r"^\S+$"
COMMAND_ID_PATTERN: Final = r"^[A-Za-z0-9]([-A-Za-z0-9_.:]*[A-Za-z0-9])?$"

# -- values that become one line of a file ---------------------------------------------

# Code points that end or break a line for some reader (C0 controls but tab, DEL, C1
# controls incl. NEL, and the Unicode line and paragraph separators).
LINE_BREAKING: Final = ((0x00, 0x08), (0x0A, 0x1F), (0x7F, 0x9F), (0x2028, 0x2029))


def _class(escape: str) -> str:
    parts = [
        escape.format(lo) if lo == hi else f"{escape.format(lo)}-{escape.format(hi)}"
        for lo, hi in LINE_BREAKING
    ]
    return "[" + "".join(parts) + "]"


LINE_BREAK_RE2: Final = _class(r"\x{{{:x}}}")
"""The class of :data:`LINE_BREAKING` in RE2 syntax (CEL ``matches``)."""
LINE_BREAK_PYTHON: Final = _class(r"\U{:08x}")
"""The same class in Python ``re`` syntax, for checks outside the API server."""

# -- connection URLs (read by roost_mavlink.pymavlink_device and the agent's links) --------

PORT: Final = (
    r"([1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5])"
)
_OCTET: Final = r"(25[0-5]|2[0-4][0-9]|1[0-9]{2}|[1-9]?[0-9])"
IPV4: Final = rf"({_OCTET}\.){{3}}{_OCTET}"
# A host name whose last label starts with a letter, so 999.1.1.1 is not a host name.
HOSTNAME: Final = (
    r"([A-Za-z0-9]([-A-Za-z0-9]{0,61}[A-Za-z0-9])?\.)*[A-Za-z]([-A-Za-z0-9]{0,61}[A-Za-z0-9])?"
)
HOST: Final = rf"({IPV4}|{HOSTNAME})"
NETWORK_SCHEMES: Final = ("udp", "udpin", "udpout", "tcp", "tcpin")
NETWORK_SCHEME_PATTERN: Final = rf"^({'|'.join(NETWORK_SCHEMES)})://"
# udp and udpin listeners may name the autopilot's address after "@" (the agent then hears
# only that sender; the port is optional, as in mavros' FCU URLs).
UDP_PEER: Final = rf"@{HOST}(:{PORT})?"
NETWORK_CONNECTION: Final = (
    rf"(^(udp|udpin)://{HOST}:{PORT}({UDP_PEER})?$)|(^(udpout|tcp|tcpin)://{HOST}:{PORT}$)"
)
DEVICE: Final = r"/dev(/[A-Za-z0-9_+-][A-Za-z0-9._+:-]*)+"
BAUD: Final = r"[1-9][0-9]{1,7}"
SERIAL_CONNECTION: Final = rf"^serial://{DEVICE}:{BAUD}$"
CONNECTION_SCHEME_PATTERN: Final = rf"^({'|'.join((*NETWORK_SCHEMES, 'serial'))})://"

# mavros' FCU URLs (its fcu_url parameter), besides the connection URLs it defaults to.
_IDS: Final = r"(/?\?ids=[0-9]{1,3},[0-9]{1,3})?"
MAVROS_SERIAL: Final = rf"^(serial|serial-hwfc)://{DEVICE}(:{BAUD})?{_IDS}$"
MAVROS_UDP: Final = rf"^(udp|udp-b|udp-pb)://({HOST})?(:{PORT})?@({HOST})?(:{PORT})?{_IDS}$"
MAVROS_TCP: Final = rf"^(tcp|tcp-l)://({HOST})?(:{PORT})?{_IDS}$"
FCU_URL_PATTERNS: Final = (
    NETWORK_CONNECTION,
    SERIAL_CONNECTION,
    MAVROS_SERIAL,
    MAVROS_UDP,
    MAVROS_TCP,
)


# -- CEL -------------------------------------------------------------------------------


def matches(expr: str, regex: str) -> str:
    """CEL: ``expr`` matches ``regex`` (a raw string literal, so no escaping)."""
    if "'" in regex:
        raise ValueError(f"a CEL raw string cannot hold a quote: {regex}")
    return f"{expr}.matches(r'{regex}')"


def rule(expr: str, message: str) -> dict[str, str]:
    """One ``x-kubernetes-validations`` entry."""
    return {"rule": expr, "message": message}


def validations(rules: Sequence[dict[str, str]]) -> JsonDict:
    """``json_schema_extra`` attaching ``rules`` to a field."""
    return {"x-kubernetes-validations": cast(list[JsonValue], list(rules))}


def label_key(expr: str) -> str:
    """CEL: ``expr`` is a label key (shape, and a prefix of at most 253 characters)."""
    return f"{matches(expr, LABEL_KEY_PATTERN)} && {matches(expr, LABEL_KEY_PREFIX_PATTERN)}"


CONNECTION_RULES: Final = [
    rule(
        matches("self", CONNECTION_SCHEME_PATTERN),
        "connection: the scheme must be udp://, udpin://, udpout://, tcp://, tcpin:// or serial://",
    ),
    rule(
        f"!{matches('self', NETWORK_SCHEME_PATTERN)} || {matches('self', NETWORK_CONNECTION)}",
        "connection: udp, udpin, udpout, tcp and tcpin take HOST:PORT, an IPv4 address or "
        "host name and a port from 1 to 65535, e.g. udp://127.0.0.1:14540; udp and udpin "
        "may add the autopilot's address as @HOST[:PORT]",
    ),
    rule(
        f"!self.startsWith('serial://') || {matches('self', SERIAL_CONNECTION)}",
        "connection: serial takes a device under /dev/ and a numeric baud, e.g. "
        "serial:///dev/ttyUSB0:921600",
    ),
]

FCU_URL_RULES: Final = [
    rule(
        " || ".join(matches("self", pattern) for pattern in FCU_URL_PATTERNS),
        "fcuUrl must be a mavros FCU URL (serial:///dev/DEVICE:BAUD, "
        "udp://[BIND]:PORT@[HOST]:PORT, tcp://HOST:PORT, tcp-l://[BIND]:PORT) or a "
        "connection URL, on one line, with ports from 1 to 65535",
    )
]

ONE_LINE_RULES: Final = [
    rule(
        f"!{matches('self', LINE_BREAK_RE2)}",
        "config values must be one line without control characters: vehicle.config holds "
        "one KEY=VALUE per line",
    )
]

CONFIG_RULES: Final = [
    rule(
        f"self.all(k, {matches('k', CONFIG_KEY_PATTERN)})",
        "config keys must be upper-case environment variable names such as MY_SETTING",
    ),
    rule(
        f"self.all(k, size(k) <= {CONFIG_KEY_MAX})",
        f"config keys are at most {CONFIG_KEY_MAX} characters",
    ),
    rule(
        "self.all(k, !k.startsWith('VEHICLE_') && !k.startsWith('ROOST_'))",
        "config keys starting with VEHICLE_ or ROOST_ are set by Roost",
    ),
    rule(
        f"self.map(k, size(k) + size(self[k])).sum() <= {CONFIG_TOTAL_MAX}",
        f"config is at most {CONFIG_TOTAL_MAX} characters of keys and values in total: "
        "Roost keeps a copy of the spec in an annotation, and annotations are limited",
    ),
]

LABEL_MAP_RULES: Final = [
    rule(
        f"self.all(k, {label_key('k')})",
        "matchLabels keys must be label keys: an optional DNS prefix (at most 253 "
        "characters) and '/', then a name of at most 63 letters, digits, '-', '_' or '.'",
    ),
]

LABEL_VALUE_RULES: Final = [
    rule(
        f"{matches('self', LABEL_VALUE_PATTERN)}",
        "label values are at most 63 letters, digits, '-', '_' or '.', starting and ending "
        "with a letter or digit",
    )
]

LABEL_REQUIREMENT_RULES: Final = [
    rule(
        label_key("self.key"),
        "matchExpressions key must be a label key: an optional DNS prefix (at most 253 "
        "characters) and '/', then a name of at most 63 letters, digits, '-', '_' or '.'",
    ),
    rule(
        "!(self.operator in ['In', 'NotIn']) || (has(self.values) && size(self.values) > 0)",
        "matchExpressions with In or NotIn need at least one value: an empty In matches no vehicle",
    ),
    rule(
        "!(self.operator in ['Exists', 'DoesNotExist']) || !has(self.values) || "
        "size(self.values) == 0",
        "matchExpressions with Exists or DoesNotExist take no values",
    ),
]
