"""Audit log lines in the API server's format (one JSON object per line), written by a test."""

from __future__ import annotations

import json
from pathlib import Path


def event(received: str, user_agent: str, verb: str, resource: str, **ref: str) -> str:
    return json.dumps(
        {
            "requestReceivedTimestamp": received,
            "userAgent": user_agent,
            "verb": verb,
            "objectRef": {"resource": resource, **ref},
            "responseStatus": {"code": 200},
        }
    )


def append(log: Path, *lines: str) -> None:
    with log.open("a") as out:
        out.writelines(line + "\n" for line in lines)
