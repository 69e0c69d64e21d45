"""Where recorded real-firmware traffic (.tlog) is found: ``$ROOST_CAPTURES_DIR``, else
``shared/captures`` beside the repository root. The recordings are read in place, never
copied in; a test that needs one skips, saying where it looked, when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CAPTURES = Path(os.environ.get("ROOST_CAPTURES_DIR") or REPO.parent / "shared" / "captures")


def capture(name: str) -> Path:
    """The recording ``name``; skips the calling test when it is not there."""
    path = CAPTURES / name
    if not path.is_file():
        pytest.skip(f"capture {name} not found in {CAPTURES} (set ROOST_CAPTURES_DIR)")
    return path
