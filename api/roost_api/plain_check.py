"""Validation for the plain (pydantic-free) API classes, as pydantic's lax mode does it.

:mod:`roost_api.plain` is generated from the pydantic models (``python -m
roost_api.plain_gen``); its loaders call these functions, one per field type, so the
rules live here once and the generated code stays a readable list of fields. Each
function takes the raw value and where it sits (``autopilots.0.sysid``, the path pydantic
reports) and returns the value converted as pydantic converts it, or raises
:class:`PlainValidationError` naming the field.

Conversions follow pydantic 2's lax mode for the values JSON, YAML and ``key=value``
flags produce: an int field takes an integral float, a bool, or a numeric string
(``" 5 "``, ``"1_000"``, ``"5.0"``); a float field a number, a bool or a numeric string;
a bool field ``0``/``1`` or the words pydantic knows (``yes``, ``off``…); a str field
only a string; a datetime an ISO 8601 string or a Unix time. ``tests/unit/
test_api_plain.py`` checks that both accept and reject the same inputs.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from datetime import UTC, datetime, timedelta
from enum import StrEnum
from typing import Any, Final, Protocol, TypeVar, get_args

E = TypeVar("E", bound=StrEnum)
T = TypeVar("T")


class Missing:
    """The marker of a field absent from the input."""

    def __repr__(self) -> str:
        return "MISSING"


MISSING: Final = Missing()


class PlainValidationError(ValueError):
    """Input that the API model would refuse; the message names the field."""

    def __init__(self, where: str, problem: str) -> None:
        super().__init__(f"{where or 'input'}: {problem}")
        self.where = where
        self.problem = problem


class ApiDocument(Protocol):
    """Anything that gives an API object's JSON: a pydantic model or a plain twin."""

    def to_api(self) -> dict[str, Any]:
        """camelCase, no nulls."""
        ...


def mapping(value: object, where: str, model: str) -> Mapping[str, Any]:
    """The input of a model: a mapping (a dict from JSON or YAML), or an API object (a
    pydantic model, say), read through its JSON."""
    if isinstance(value, Mapping):
        return value
    to_api = getattr(value, "to_api", None)
    if callable(to_api):
        document = to_api()
        if isinstance(document, Mapping):
            return document
    raise PlainValidationError(where, f"Input should be a valid dictionary or {model}")


def get(doc: Mapping[str, Any], alias: str, name: str) -> object:
    """The field's raw value by its camelCase name or its Python name, or MISSING."""
    if alias in doc:
        return doc[alias]
    return doc.get(name, MISSING)


def required(value: object, where: str) -> object:
    """``value``, which must be present."""
    if value is MISSING:
        raise PlainValidationError(where, "Field required")
    return value


def _finite(value: float, where: str) -> float:
    if not math.isfinite(value):
        raise PlainValidationError(where, "Input should be a finite number")
    return value


_INT_TEXT = re.compile(r"[+-]?[0-9]+(_[0-9]+)*(\.0*)?")


def integer(
    value: object,
    where: str,
    *,
    ge: float | None = None,
    le: float | None = None,
    gt: float | None = None,
    lt: float | None = None,
) -> int:
    """An int field."""
    result: int
    if isinstance(value, bool | int):
        result = int(value)
    elif isinstance(value, float):
        if not _finite(value, where).is_integer():
            raise PlainValidationError(
                where, "Input should be a valid integer, got a number with a fractional part"
            )
        result = int(value)
    elif isinstance(value, str) and _INT_TEXT.fullmatch(value.strip()):
        result = int(value.strip().partition(".")[0])
    elif isinstance(value, str):
        raise PlainValidationError(
            where, "Input should be a valid integer, unable to parse string as an integer"
        )
    else:
        raise PlainValidationError(where, "Input should be a valid integer")
    return _bounded(result, where, ge=ge, le=le, gt=gt, lt=lt)


def number(
    value: object,
    where: str,
    *,
    ge: float | None = None,
    le: float | None = None,
    gt: float | None = None,
    lt: float | None = None,
) -> float:
    """A float field (infinities and NaN pass, as in pydantic, unless a bound refuses)."""
    if isinstance(value, bool | int | float):
        result = float(value)
    elif isinstance(value, str):
        try:
            result = float(value.strip())
        except ValueError:
            raise PlainValidationError(
                where, "Input should be a valid number, unable to parse string as a number"
            ) from None
    else:
        raise PlainValidationError(where, "Input should be a valid number")
    return _bounded(result, where, ge=ge, le=le, gt=gt, lt=lt)


N = TypeVar("N", int, float)


def _bounded(
    value: N,
    where: str,
    *,
    ge: float | None,
    le: float | None,
    gt: float | None,
    lt: float | None,
) -> N:
    # Written as "not (value OP bound)" so that NaN fails every bound, as in pydantic.
    if ge is not None and not value >= ge:
        raise PlainValidationError(where, f"Input should be greater than or equal to {ge}")
    if gt is not None and not value > gt:
        raise PlainValidationError(where, f"Input should be greater than {gt}")
    if le is not None and not value <= le:
        raise PlainValidationError(where, f"Input should be less than or equal to {le}")
    if lt is not None and not value < lt:
        raise PlainValidationError(where, f"Input should be less than {lt}")
    return value


_TRUE_WORDS = frozenset({"1", "on", "t", "true", "y", "yes"})
_FALSE_WORDS = frozenset({"0", "off", "f", "false", "n", "no"})


def boolean(value: object, where: str) -> bool:
    """A bool field."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int | float) and value in (0, 1):
        return bool(value)
    if isinstance(value, str):
        word = value.lower()
        if word in _TRUE_WORDS:
            return True
        if word in _FALSE_WORDS:
            return False
    raise PlainValidationError(where, "Input should be a valid boolean")


_PATTERNS: dict[str, re.Pattern[str]] = {}


def text(
    value: object,
    where: str,
    *,
    min_length: int | None = None,
    max_length: int | None = None,
    pattern: str | None = None,
) -> str:
    """A str field."""
    if not isinstance(value, str):
        raise PlainValidationError(where, "Input should be a valid string")
    if min_length is not None and len(value) < min_length:
        raise PlainValidationError(where, f"String should have at least {min_length} characters")
    if max_length is not None and len(value) > max_length:
        raise PlainValidationError(where, f"String should have at most {max_length} characters")
    if pattern is not None:
        compiled = _PATTERNS.get(pattern) or _PATTERNS.setdefault(pattern, re.compile(pattern))
        if not compiled.search(value):
            raise PlainValidationError(where, f"String should match pattern '{pattern}'")
    return value


def choice(value: object, where: str, literal: Any) -> Any:
    """A field of a ``Literal`` of strings (given the Literal): one of its values."""
    allowed = get_args(literal)
    if isinstance(value, str) and value in allowed:
        return value
    options = " or ".join(repr(a) for a in allowed)
    raise PlainValidationError(where, f"Input should be {options}")


def member(value: object, where: str, enum: type[E]) -> E:
    """A StrEnum field, given its value."""
    if isinstance(value, str):
        try:
            return enum(value)
        except ValueError:
            pass
    options = ", ".join(repr(e.value) for e in enum)
    raise PlainValidationError(where, f"Input should be one of {options}")


_UNIX_TEXT = re.compile(r"[+-]?[0-9]+(\.[0-9]*)?")
_UNIX_MS_ABOVE = 2e10  # pydantic reads larger Unix times as milliseconds


def moment(value: object, where: str) -> datetime:
    """A datetime field: an ISO 8601 string or a Unix time (seconds, or ms when large)."""
    if isinstance(value, datetime):
        return value
    if isinstance(value, str) and _UNIX_TEXT.fullmatch(value):
        value = float(value)
    if isinstance(value, int | float) and not isinstance(value, bool):
        seconds = float(value)
        if not math.isfinite(seconds):
            raise PlainValidationError(where, "Input should be a valid datetime")
        if abs(seconds) > _UNIX_MS_ABOVE:
            seconds /= 1000
        return datetime(1970, 1, 1, tzinfo=UTC) + timedelta(seconds=seconds)
    if isinstance(value, str):
        try:
            parsed = datetime.fromisoformat(value)
        except ValueError:
            pass
        else:
            return parsed
    raise PlainValidationError(where, "Input should be a valid datetime")


def items(
    value: object,
    where: str,
    item: Callable[[object, str], T],
    *,
    min_length: int | None = None,
    max_length: int | None = None,
) -> list[T]:
    """A list field, each item checked by ``item(value, where)``."""
    if not isinstance(value, list | tuple):
        raise PlainValidationError(where, "Input should be a valid list")
    if min_length is not None and len(value) < min_length:
        raise PlainValidationError(
            where, f"List should have at least {min_length} items after validation"
        )
    if max_length is not None and len(value) > max_length:
        raise PlainValidationError(
            where, f"List should have at most {max_length} items after validation"
        )
    return [item(v, f"{where}.{i}") for i, v in enumerate(value)]


def iso(value: datetime) -> str:
    """A datetime as pydantic writes it to JSON (UTC as ``Z``)."""
    text = value.isoformat()
    return text[:-6] + "Z" if text.endswith("+00:00") else text


def without_nones(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` without None members, recursively (pydantic's ``exclude_none``)."""
    return {key: _without_nones_in(value) for key, value in doc.items() if value is not None}


def _without_nones_in(value: object) -> object:
    if isinstance(value, dict):
        return without_nones(value)
    if isinstance(value, list):
        return [_without_nones_in(v) for v in value]
    return value
