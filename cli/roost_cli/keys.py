"""``roost keys``: each Vehicle's MAVLink signing key in a Secret of its own.

Why a passphrase: MAVProxy (``signing key PASSPHRASE``) and QGroundControl take a text
from the user and sign with its SHA-256, so a key made that way can be typed into a
ground station; a key of 32 random bytes cannot. The passphrase is 32 random URL-safe
characters (192 bits), so the derived key is as strong as a random one.

The Secret (``roost-signing-<vehicle>``, type ``roost.dev/mavlink-signing``) holds
``key`` (64 hex digits, what the agent reads), ``passphrase`` (for ground stations) and
``previous`` (the key before the last rotation, empty at first): after ``rotate`` the
agent signs with the new key and still takes the previous one, answering each peer with
the key it proved, so autopilots and ground stations can be moved to the new key one by
one. Nothing here prints or logs a key or a passphrase.

The manifest and the rotation are pure functions (tests/unit/test_cli_keys.py); the
commands only read and write the Secret.
"""

from __future__ import annotations

import hashlib
import secrets
from collections.abc import Mapping
from typing import Any, Final

from roost_api.wellknown import SIGNING_SECRET_PREFIX

SECRET_TYPE: Final = "roost.dev/mavlink-signing"
LABEL_VEHICLE: Final = "roost.dev/vehicle"
PASSPHRASE_BYTES: Final = 24  # 32 URL-safe characters


def secret_name(vehicle: str) -> str:
    """The Secret that holds ``vehicle``'s key (the chart mounts it by this name)."""
    return f"{SIGNING_SECRET_PREFIX}{vehicle}"


def new_passphrase() -> str:
    return secrets.token_urlsafe(PASSPHRASE_BYTES)


def key_entries(passphrase: str, previous_key_hex: str = "") -> dict[str, str]:
    """The Secret's ``stringData`` for ``passphrase``."""
    return {
        # SHA-256 of the ASCII text: roost_mavlink.signing.passphrase_key, which the CLI
        # does not import (tests/unit/test_repo_import_directions.py); a test checks both agree
        "key": hashlib.sha256(passphrase.encode("ascii")).hexdigest(),
        "passphrase": passphrase,
        "previous": previous_key_hex,
    }


def key_secret(vehicle: str, namespace: str, passphrase: str) -> dict[str, Any]:
    """A new key Secret for ``vehicle``."""
    return {
        "apiVersion": "v1",
        "kind": "Secret",
        "metadata": {
            "name": secret_name(vehicle),
            "namespace": namespace,
            "labels": {LABEL_VEHICLE: vehicle, "app.kubernetes.io/part-of": "roost"},
        },
        "type": SECRET_TYPE,
        "stringData": key_entries(passphrase),
    }


def rotation_patch(current: Mapping[str, Any], passphrase: str) -> dict[str, Any]:
    """The merge patch that rotates ``current`` (a live key Secret) to ``passphrase``:
    the current key becomes ``previous``."""
    import base64  # noqa: PLC0415

    encoded = (current.get("data") or {}).get("key", "")
    old = base64.b64decode(encoded).decode("ascii").strip() if encoded else ""
    return {"stringData": key_entries(passphrase, old)}
