"""Generate :mod:`roost_api.plain` from the pydantic models the node agent reads and writes.

Why: the pydantic models are the single source of truth (CRDs, operator, CLI), but
``import pydantic`` and the model classes would be a large share of a standalone node
agent's memory on a companion computer (docs/performance.md#memory). The agent needs
only a dozen of the models, and needs them validated exactly as the API would validate
them. So this writes them out once as frozen dataclasses with the same class and
attribute names, each with a ``from_api`` loader (types, enums, required fields,
defaults, bounds, lengths, patterns; unknown fields ignored) built from the model's own
field metadata, and a ``to_api`` that gives the model's JSON. The field rules are
interpreted by the hand-written :mod:`roost_api.plain_check`, one function per field
type.

Run ``python -m roost_api.plain_gen`` after changing a model in :data:`MODELS`;
``tests/unit/test_api_plain.py`` fails while the committed module differs from what
this renders, and checks that the plain loaders and pydantic accept and reject the same
inputs.

This is the one way to declare a pydantic-free class with a validating loader. Other
packages' classes of that kind (the agent's state file) are declared as pydantic models
in a module of their own that defines ``MODELS`` and ``TARGET`` like this one, and are
written with ``python -m roost_api.plain_gen <module>``; classes of the API they contain
are imported from :mod:`roost_api.plain`. Generating rather than interpreting a table of
fields at run time keeps the loaders plain code (fast, readable, type-checked), and
needs no second description of a field beside the pydantic one.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import types
import typing
from collections.abc import Sequence
from datetime import datetime
from enum import Enum, StrEnum
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from roost_api import autopilot, core, meta

TARGET = Path(__file__).with_name("plain.py")

MODELS: tuple[type[meta.ApiModel], ...] = (
    meta.Condition,
    autopilot.AutopilotSpec,
    autopilot.Thresholds,
    autopilot.SafetyRoutine,
    autopilot.StandbyLimits,
    autopilot.HubEndpoint,
    autopilot.HubSpec,
    autopilot.FailoverPolicy,
    autopilot.AutopilotCommand,
    autopilot.ParameterValue,
    autopilot.ParametersSpec,
    autopilot.FirmwareRequirement,
    autopilot.FencePoint,
    autopilot.FenceCircle,
    autopilot.Fence,
    autopilot.AssignedFence,
    autopilot.RedundantAutopilotSpec,
    autopilot.FirmwareInfo,
    autopilot.AutopilotHealth,
    autopilot.FailoverRecord,
    autopilot.CommandResult,
    autopilot.HubEndpointStatus,
    autopilot.RedundantAutopilotStatus,
)
"""The models to write out, each after the models it contains."""

_NAMED_LITERALS = {get_args(core.ConditionStatus): "ConditionStatus"}


class _Module:
    """What the generated module defines (``local``) and imports."""

    def __init__(self, local: Sequence[type[BaseModel]]) -> None:
        self.local = frozenset(local)
        self.imports: dict[str, set[str]] = {}

    def use(self, module: str, name: str) -> str:
        self.imports.setdefault(module, set()).add(name)
        return name


def _optional_inner(annotation: Any) -> tuple[Any, bool]:
    """(the type without None, whether None is allowed)."""
    if get_origin(annotation) in (Union, types.UnionType):
        args = [a for a in get_args(annotation) if a is not type(None)]
        if len(args) == 1 and len(get_args(annotation)) == 2:
            return args[0], True
        raise TypeError(f"unsupported union {annotation}")
    return annotation, False


def _type_name(annotation: Any, mod: _Module) -> str:
    inner, optional = _optional_inner(annotation)
    if get_origin(inner) is list:
        (item,) = get_args(inner)
        name = f"list[{_type_name(item, mod)}]"
    elif get_origin(inner) is Literal:
        name = mod.use("roost_api.core", _NAMED_LITERALS[get_args(inner)])
    elif isinstance(inner, type) and issubclass(inner, StrEnum):
        name = mod.use(inner.__module__, inner.__name__)
    elif isinstance(inner, type) and issubclass(inner, BaseModel):
        name = inner.__name__
        if inner not in mod.local:
            mod.use("roost_api.plain", name)
    elif inner is datetime:
        name = mod.use("datetime", "datetime")
    elif inner in (str, int, float, bool):
        name = inner.__name__
    else:
        raise TypeError(f"unsupported field type {inner}")
    return f"{name} | None" if optional else name


def _constraints(info: FieldInfo) -> str:
    """The field's bounds, lengths and pattern as keyword arguments."""
    out: list[str] = []
    for item in info.metadata:
        for attr in ("ge", "le", "gt", "lt", "min_length", "max_length", "pattern"):
            value = getattr(item, attr, None)
            known = isinstance(item, annotated_types.BaseMetadata) or (
                type(item).__name__ == "_PydanticGeneralMetadata"  # pydantic's pattern holder
            )
            if value is not None and known:
                out.append(f"{attr}={value!r}")
    return "".join(f", {c}" for c in out)


def _check(
    annotation: Any, value: str, where: str, info: FieldInfo | None, *, absent: bool = False
) -> str:
    """An expression converting ``value`` (an object) to the field's type; with ``absent``,
    an optional field's ``check.MISSING`` reads as None too."""
    inner, optional = _optional_inner(annotation)
    limits = _constraints(info) if info is not None else ""
    if get_origin(inner) is list:
        (item,) = get_args(inner)
        item_check = _check(item, "x", "w", None)
        simple = item_check.removesuffix("(x, w)")
        item_fn = simple if simple != item_check else f"lambda x, w: {item_check}"
        expr = f"check.items({value}, {where}, {item_fn}{limits})"
    elif get_origin(inner) is Literal:
        expr = f"check.choice({value}, {where}, {_NAMED_LITERALS[get_args(inner)]})"
    elif isinstance(inner, type) and issubclass(inner, StrEnum):
        expr = f"check.member({value}, {where}, {inner.__name__})"
    elif isinstance(inner, type) and issubclass(inner, BaseModel):
        expr = f'{inner.__name__}.from_api({value}, {where} + ".")'
    elif inner is datetime:
        expr = f"check.moment({value}, {where}{limits})"
    else:
        kind = {str: "text", int: "integer", float: "number", bool: "boolean"}[inner]
        expr = f"check.{kind}({value}, {where}{limits})"
    if not optional:
        return expr
    missing = f" or {value} is check.MISSING" if absent else ""
    return f"None if {value} is None{missing} else {expr}"


def _dump(annotation: Any, value: str) -> str:
    """An expression giving the JSON form of ``value`` (of the field's type)."""
    inner, optional = _optional_inner(annotation)
    if get_origin(inner) is list:
        (item,) = get_args(inner)
        expr = f"[{_dump(item, 'x')} for x in {value}]"
    elif isinstance(inner, type) and issubclass(inner, StrEnum):
        expr = f"{value}.value"
    elif isinstance(inner, type) and issubclass(inner, BaseModel):
        expr = f"{value}.api_dump()"
    elif inner is datetime:
        expr = f"check.iso({value})"
    else:
        return value
    return f"None if {value} is None else {expr}" if optional else expr


def _default(info: FieldInfo) -> str | None:
    """The default as an expression (a new object for a factory), or None if required."""
    if info.default_factory is not None:
        factory = typing.cast(type, info.default_factory)
        return f"{factory.__name__}()"
    if info.default is PydanticUndefined:
        return None
    if isinstance(info.default, Enum):
        return f"{type(info.default).__name__}.{info.default.name}"
    return repr(info.default)


def _alias(model: type[BaseModel], name: str, info: FieldInfo) -> str:
    alias = info.alias or info.serialization_alias
    return alias if alias else name


def _render_model(model: type[BaseModel], mod: _Module) -> list[str]:
    doc = (model.__doc__ or "").strip().splitlines()[0]
    lines = [
        "@dataclass(frozen=True, slots=True, kw_only=True)",
        f"class {model.__name__}:",
        f'    """{doc}',
        "",
        f"    Plain twin of :class:`{model.__module__}.{model.__name__}`.",
        '    """',
        "",
    ]
    fields = model.model_fields
    for name, info in fields.items():
        type_name = _type_name(info.annotation, mod)
        default = _default(info)
        if info.default_factory is not None:
            factory = typing.cast(type, info.default_factory).__name__
            lines.append(f"    {name}: {type_name} = field(default_factory={factory})")
        elif default is not None:
            lines.append(f"    {name}: {type_name} = {default}")
        else:
            lines.append(f"    {name}: {type_name}")
    lines += [
        "",
        "    @classmethod",
        f'    def from_api(cls, doc: object, at: str = "") -> {model.__name__}:',
        '        """Validate a camelCase mapping as the API model would; ``at`` prefixes field',
        '        paths in errors."""',
        "        if isinstance(doc, cls):",
        "            return doc",
        f'        d = check.mapping(doc, at.rstrip("."), "{model.__name__}")',
    ]
    for name, info in fields.items():
        alias = _alias(model, name, info)
        where = f'at + "{alias}"'
        default = _default(info)
        if default is None:
            lines.append(f'        v = check.required(check.get(d, "{alias}", "{name}"), {where})')
            lines.append(f"        {name} = {_check(info.annotation, 'v', where, info)}")
        else:
            lines.append(f'        v = check.get(d, "{alias}", "{name}")')
            if default == "None" and _optional_inner(info.annotation)[1]:
                value = _check(info.annotation, "v", where, info, absent=True)
            else:
                checked = _check(info.annotation, "v", where, info)
                value = f"{default} if v is check.MISSING else {checked}"
            lines.append(f"        {name} = {value}")
    lines.append("        return cls(" + ", ".join(f"{n}={n}" for n in fields) + ")")
    lines += [
        "",
        "    def api_dump(self) -> dict[str, Any]:",
        '        """Every field by its camelCase name, None included."""',
        "        return {",
    ]
    for name, info in fields.items():
        value = _dump(info.annotation, f"self.{name}")
        lines.append(f'            "{_alias(model, name, info)}": {value},')
    lines += [
        "        }",
        "",
        "    def to_api(self) -> dict[str, Any]:",
        '        """The JSON body Kubernetes expects: camelCase, no nulls (as the model\'s)."""',
        "        return check.without_nones(self.api_dump())",
    ]
    return lines


def render(
    models: Sequence[type[BaseModel]] = MODELS, target: Path = TARGET, source: str = ""
) -> str:
    """The source of the module of ``models`` (:mod:`roost_api.plain` by default),
    formatted; ``source`` names the module declaring them, if not this one."""
    mod = _Module(models)
    mod.use("dataclasses", "dataclass")
    mod.use("dataclasses", "field")
    mod.use("typing", "Any")
    body: list[str] = []
    for model in models:
        body += ["", "", *_render_model(model, mod)]
    head = [
        f'"""Generated by ``python -m roost_api.plain_gen {source}``: do not edit.'
        if source
        else '"""Generated by ``python -m roost_api.plain_gen`` from the pydantic models: '
        "do not edit.",
        "",
        "Plain frozen dataclasses for the node agent, which runs without pydantic; see",
        ":mod:`roost_api.plain_gen` for why and :mod:`roost_api.plain_check` for the rules.",
        '"""',
        "",
        "from __future__ import annotations",
        "",
    ]
    for module in sorted(mod.imports):
        head.append(f"from {module} import {', '.join(sorted(mod.imports[module]))}")
    head.append("from roost_api import plain_check as check")
    return _formatted("\n".join(head + body) + "\n", target)


def _formatted(source: str, target: Path) -> str:
    """``source`` through ruff (import order and format), as committed."""
    ruff = [sys.executable, "-m", "ruff"]
    fixed = subprocess.run(
        [*ruff, "check", "--fix", "--quiet", "--stdin-filename", str(target), "-"],
        input=source,
        capture_output=True,
        text=True,
        check=False,
    ).stdout
    return subprocess.run(
        [*ruff, "format", "--stdin-filename", str(target), "-"],
        input=fixed,
        capture_output=True,
        text=True,
        check=True,
    ).stdout


def render_declared(source: str) -> tuple[Path, str]:
    """(target, source text) for the module ``source`` declaring ``MODELS`` and ``TARGET``."""
    declared = importlib.import_module(source)
    return declared.TARGET, render(declared.MODELS, declared.TARGET, source)


def main(argv: Sequence[str]) -> int:
    target, text = render_declared(argv[0]) if argv else (TARGET, render())
    target.write_text(text)
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
