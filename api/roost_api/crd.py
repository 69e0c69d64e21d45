"""Generate the CustomResourceDefinitions in ``crds/`` from the pydantic models.

``python -m roost_api.crd crds/`` (``make crds``) writes one YAML file per kind; a test
fails when the committed files differ from what this produces, so the models stay the
single source of truth.

Pydantic emits JSON Schema 2020-12; Kubernetes wants a *structural* OpenAPI v3 subset:
every node typed, no ``$ref``/``anyOf`` for nullability, ``exclusiveMinimum`` as a flag.
:func:`structural` performs that translation and keeps ``x-kubernetes-*`` extensions
(CEL rules, list types) that the models attach with ``json_schema_extra``.

Mission pod templates embed the real ``PodTemplateSpec`` schema of the pinned Kubernetes
version, read from the ``kubernetes-validate`` package's definitions. Field descriptions
inside the embedded schema are dropped: with them each template adds ~0.5 MB, which
pushes the CRD past what client-side ``kubectl apply`` can store in its
last-applied annotation (256 KiB). ``kubectl explain`` still lists every field and type.
No ``x-kubernetes-preserve-unknown-fields`` is needed anywhere. Template metadata is
limited to labels and annotations, as a Job template effectively is.
"""

from __future__ import annotations

import argparse
import json
import sys
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from roost_api.resources import KINDS, ResourceKind

KUBERNETES_SCHEMA_VERSION = "v1.35.0"

_KEEP = {
    "type",
    "properties",
    "required",
    "items",
    "additionalProperties",
    "description",
    "enum",
    "format",
    "minimum",
    "maximum",
    "minLength",
    "maxLength",
    "pattern",
    "minItems",
    "maxItems",
    "minProperties",
    "maxProperties",
    "default",
}

_TEMPLATE_METADATA: dict[str, Any] = {
    "type": "object",
    "description": "Labels and annotations for the pods.",
    "properties": {
        "labels": {"type": "object", "additionalProperties": {"type": "string"}},
        "annotations": {"type": "object", "additionalProperties": {"type": "string"}},
    },
}
_INT_OR_STRING_DEFS = {
    "io.k8s.apimachinery.pkg.util.intstr.IntOrString",
    "io.k8s.apimachinery.pkg.api.resource.Quantity",
}


class SchemaError(ValueError):
    """The models produced a schema this generator cannot make structural."""


def _kubernetes_definitions() -> dict[str, Any]:
    path = (
        resources.files("kubernetes_validate")
        / "kubernetes-json-schema"
        / f"{KUBERNETES_SCHEMA_VERSION}-local"
        / "_definitions.json"
    )
    defs: dict[str, Any] = json.loads(path.read_text())["$defs"]
    return defs


def _non_null_type(value: Any) -> Any:
    if isinstance(value, list):
        types = [t for t in value if t != "null"]
        if len(types) != 1:
            raise SchemaError(f"ambiguous type {value}")
        return types[0]
    return value


def embed_kubernetes(name: str, defs: dict[str, Any], *, top: bool = True) -> dict[str, Any]:
    """The structural schema of a Kubernetes definition, refs inlined, descriptions dropped."""
    if name == "io.k8s.apimachinery.pkg.apis.meta.v1.ObjectMeta":
        return dict(_TEMPLATE_METADATA)
    if name in _INT_OR_STRING_DEFS:
        return {"x-kubernetes-int-or-string": True}
    return _embed_node(defs[name], defs, keep_description=top)


def _embed_node(
    node: dict[str, Any], defs: dict[str, Any], *, keep_description: bool
) -> dict[str, Any]:
    if "$ref" in node:
        return embed_kubernetes(node["$ref"].rsplit("/", 1)[-1], defs, top=False)
    if "oneOf" in node:
        kinds = {_non_null_type(branch.get("type")) for branch in node["oneOf"]}
        if kinds <= {"string", "integer", "number"}:
            return {"x-kubernetes-int-or-string": True}
        raise SchemaError(f"unsupported oneOf {kinds}")
    out: dict[str, Any] = {}
    node_type = _non_null_type(node.get("type"))
    if node_type is None:
        raise SchemaError(f"untyped Kubernetes schema node {node}")
    out["type"] = node_type
    if keep_description and "description" in node:
        out["description"] = node["description"]
    for key in ("format", "required"):
        if key in node:
            out[key] = node[key]
    if "enum" in node:
        out["enum"] = [v for v in node["enum"] if v is not None]
    if "properties" in node:
        out["properties"] = {
            k: _embed_node(v, defs, keep_description=False) for k, v in node["properties"].items()
        }
    if isinstance(node.get("additionalProperties"), dict):
        out["additionalProperties"] = _embed_node(
            node["additionalProperties"], defs, keep_description=False
        )
    if "items" in node:
        out["items"] = _embed_node(node["items"], defs, keep_description=False)
    return out


def structural(
    node: dict[str, Any], defs: dict[str, Any], k8s_defs: dict[str, Any]
) -> dict[str, Any]:
    """Translate one pydantic JSON-schema node into a structural OpenAPI v3 node."""
    node = dict(node)
    if "$ref" in node:
        target = defs[node.pop("$ref").rsplit("/", 1)[-1]]
        merged = {**target, **node}  # the field's own description wins
        return structural(merged, defs, k8s_defs)
    if "anyOf" in node:
        branches = [b for b in node.pop("anyOf") if b.get("type") != "null"]
        if len(branches) != 1:
            raise SchemaError(f"anyOf with {len(branches)} non-null branches")
        node.pop("default", None)  # the null default of an Optional field
        return structural({**branches[0], **node}, defs, k8s_defs)
    if "x-roost-embed" in node:
        embedded = embed_kubernetes(node["x-roost-embed"], k8s_defs)
        if "description" in node:
            embedded["description"] = node["description"]
        return embedded

    out: dict[str, Any] = {}
    for key, value in node.items():
        if key in _KEEP or key.startswith("x-kubernetes-"):
            out[key] = value
    if "exclusiveMinimum" in node:
        out["minimum"] = node["exclusiveMinimum"]
        out["exclusiveMinimum"] = True
    if "exclusiveMaximum" in node:
        out["maximum"] = node["exclusiveMaximum"]
        out["exclusiveMaximum"] = True
    if "properties" in node:
        out["properties"] = {
            k: structural(v, defs, k8s_defs) for k, v in node["properties"].items()
        }
    if isinstance(node.get("additionalProperties"), dict):
        out["additionalProperties"] = structural(node["additionalProperties"], defs, k8s_defs)
    elif "additionalProperties" in node:
        del out["additionalProperties"]
        if node["additionalProperties"] is True and "properties" not in node:
            out["x-kubernetes-preserve-unknown-fields"] = True
    if "items" in node:
        out["items"] = structural(node["items"], defs, k8s_defs)
    if "type" not in out and not out.get("x-kubernetes-preserve-unknown-fields"):
        raise SchemaError(f"untyped schema node {node}")
    return out


def model_schema(model: type[Any], k8s_defs: dict[str, Any]) -> dict[str, Any]:
    """Structural schema of a pydantic model (by alias, as it appears on the wire)."""
    raw = model.model_json_schema(by_alias=True, mode="validation")
    defs = raw.pop("$defs", {})
    return structural(raw, defs, k8s_defs)


def build_crd(kind: ResourceKind, k8s_defs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The CustomResourceDefinition of one kind, as a plain dict."""
    k8s_defs = k8s_defs if k8s_defs is not None else _kubernetes_definitions()
    spec = model_schema(kind.spec_model, k8s_defs)
    spec["description"] = f"Desired state of the {kind.kind}."
    if kind.spec_rules:
        spec["x-kubernetes-validations"] = [
            *spec.get("x-kubernetes-validations", []),
            *kind.spec_rules,
        ]
    status = model_schema(kind.status_model, k8s_defs)
    status["description"] = f"Observed state of the {kind.kind}."
    root: dict[str, Any] = {
        "type": "object",
        "description": kind.description,
        "required": ["spec"],
        "properties": {
            "apiVersion": {"type": "string"},
            "kind": {"type": "string"},
            "metadata": {"type": "object"},
            "spec": spec,
            "status": status,
        },
    }
    if kind.root_rules:
        root["x-kubernetes-validations"] = list(kind.root_rules)
    return {
        "apiVersion": "apiextensions.k8s.io/v1",
        "kind": "CustomResourceDefinition",
        "metadata": {
            "name": kind.crd_name,
            "labels": {"app.kubernetes.io/part-of": "roost"},
        },
        "spec": {
            "group": kind.group,
            "scope": kind.scope,
            "names": {
                "kind": kind.kind,
                "listKind": f"{kind.kind}List",
                "plural": kind.plural,
                "singular": kind.singular,
                "shortNames": list(kind.short_names),
                "categories": list(kind.categories),
            },
            "versions": [
                {
                    "name": kind.version,
                    "served": True,
                    "storage": True,
                    "subresources": {"status": {}},
                    "additionalPrinterColumns": [c.to_crd() for c in kind.columns],
                    "schema": {"openAPIV3Schema": root},
                }
            ],
        },
    }


def render(kind: ResourceKind, k8s_defs: dict[str, Any] | None = None) -> str:
    """The YAML text written to ``crds/<group>_<plural>.yaml``."""
    header = "# Generated by `make crds` from api/roost_api; do not edit by hand.\n"
    body = yaml.safe_dump(build_crd(kind, k8s_defs), sort_keys=False, width=100)
    return header + body


def file_name(kind: ResourceKind) -> str:
    return f"{kind.group}_{kind.plural}.yaml"


def generate_all() -> dict[str, str]:
    """File name → YAML text for every kind."""
    k8s_defs = _kubernetes_definitions()
    return {file_name(kind): render(kind, k8s_defs) for kind in KINDS}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Generate Roost's CRDs from the models.")
    parser.add_argument("out_dir", type=Path, help="directory to write the CRD YAML files to")
    parser.add_argument("--check", action="store_true", help="fail if files differ")
    args = parser.parse_args(argv)
    stale = []
    for name, text in generate_all().items():
        path = args.out_dir / name
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
            continue
        args.out_dir.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {path}")
    if stale:
        print(f"out of date (run `make crds`): {', '.join(stale)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
