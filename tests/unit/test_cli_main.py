"""The ``roost`` command line's number options: ``finite`` refuses what is not a finite
number in range, and every numeric fault's range is one it can express.

The real console script's one-line errors are in ``tests/integration/test_cli_errors.py``.
"""

from __future__ import annotations

import math

import pytest
import typer

from roost_cli.errors import CliError
from roost_cli.main import finite
from roost_cli.sandbox.sims import fault_message
from roost_sim.faults import NUMERIC_RANGES, FaultKind, check_value


@pytest.mark.parametrize("text", ["inf", "-inf", "nan", "1e999", "-0.5", "10.5"])
def test_finite_refuses_what_is_not_a_finite_number_in_range(text: str) -> None:
    with pytest.raises(typer.BadParameter):
        finite(0, 10)(text)


def test_finite_passes_numbers_in_range() -> None:
    assert finite(0, 10)("0") == 0.0
    assert finite(0, 10)("1e1") == 10.0


@pytest.mark.parametrize("kind", sorted(NUMERIC_RANGES))
def test_every_numeric_fault_refuses_infinite_and_out_of_range_values(kind: FaultKind) -> None:
    low, high, _ = NUMERIC_RANGES[kind]
    for bad in ("inf", "-inf", "nan", str(high * 2 + 1), str(low - 1), "x"):
        with pytest.raises(ValueError):
            check_value(kind, bad)
        with pytest.raises(CliError, match="--value"):
            fault_message(kind.value, bad)
    check_value(kind, str(high))
    check_value(kind, None)
    assert math.isfinite(high)
    assert fault_message(kind.value, str(low)) == {
        "op": "fault",
        "kind": kind.value,
        "value": str(low),
    }
