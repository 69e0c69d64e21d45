"""The committed plain API modules of the node agent are what the generator renders now.

The generator formats its output with the real ``ruff`` (a program), so this runs it;
the generated loaders against the models are in ``tests/unit/test_api_plain.py``.
"""

from __future__ import annotations

from roost_agent import state_model
from roost_api.plain_gen import TARGET, render, render_declared


def test_the_committed_module_is_what_the_generator_renders() -> None:
    """Regenerate with ``python -m roost_api.plain_gen`` when this fails."""
    assert TARGET.read_text() == render()


def test_the_committed_state_module_is_what_the_generator_renders() -> None:
    """Regenerate with ``python -m roost_api.plain_gen roost_agent.state_model``."""
    target, text = render_declared("roost_agent.state_model")
    assert target == state_model.TARGET
    assert target.read_text() == text
