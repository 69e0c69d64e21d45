"""``roost keys``: the Secret it writes and how a rotation changes it (no cluster)."""

from __future__ import annotations

import base64
import hashlib

from roost_cli import keys
from roost_mavlink.signing import passphrase_key


def test_a_key_secret_holds_the_passphrase_and_its_sha256() -> None:
    secret = keys.key_secret("drone-1", "roost-system", "correct horse")
    assert secret["metadata"]["name"] == "roost-signing-drone-1"
    assert secret["metadata"]["labels"]["roost.dev/vehicle"] == "drone-1"
    assert secret["type"] == "roost.dev/mavlink-signing"
    data = secret["stringData"]
    assert data["key"] == hashlib.sha256(b"correct horse").hexdigest()  # what MAVProxy uses
    assert (data["passphrase"], data["previous"]) == ("correct horse", "")
    assert bytes.fromhex(data["key"]) == passphrase_key("correct horse")  # what the hub uses


def test_passphrases_are_long_random_and_typeable() -> None:
    made = {keys.new_passphrase() for _ in range(50)}
    assert len(made) == 50
    assert all(len(p) == 32 and p.isascii() and " " not in p for p in made)


def test_a_rotation_keeps_the_current_key_as_previous() -> None:
    old = hashlib.sha256(b"old").hexdigest()
    live = {"data": {"key": base64.b64encode(old.encode()).decode(), "previous": ""}}
    patch = keys.rotation_patch(live, "new")
    assert patch == {
        "stringData": {
            "key": hashlib.sha256(b"new").hexdigest(),
            "passphrase": "new",
            "previous": old,
        }
    }
