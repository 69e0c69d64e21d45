"""The packages depend on each other in one direction only, checked on the source.

    roost_api  ←  roost_kube  ←  roost_agent / roost_operator / roost_cli

``roost_api`` (the contract) imports no other Roost package; the Kubernetes layer only
the API; the agent, the operator and the CLI never each other, and the operator never the
MAVLink package (what it needs of the vehicles, such as landed-state names and the SITL
port scheme, is part of the contract). The sandbox
(``roost_cli.sandbox``) is the one product part that may start the local control plane
and the simulators. Nothing shipped imports ``tests`` or ``bench``; kopf is the
operator's alone, and the Kubernetes layer imports the ``kubernetes`` client at module
level only in the modules the agent loads in cluster mode. Every request goes through
``roost_kube.Kube``: only the Kubernetes layer (and the CLI's kubeconfig loading) imports
the ``kubernetes`` package.

Inside the operator, the failover decision (``roost_operator.autopilots``) knows nothing of
Vehicles: the Vehicle's plan hands it what it needs (the URL mavros uses for each
autopilot, whether mavros rolled out), so the two packages never import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from roost_localcluster.binaries import REPO_ROOT

PACKAGES = {
    "roost_api": "api",
    "roost_kube": "kube",
    "roost_mavlink": "mavlink",
    "roost_sim": "sim",
    "roost_agent": "agent",
    "roost_operator": "operator",
    "roost_cli": "cli",
    "roost_localcluster": "localcluster",
}
ALLOWED: dict[str, set[str]] = {
    "roost_api": set(),
    "roost_kube": {"roost_api"},
    "roost_mavlink": {"roost_api"},
    "roost_sim": {"roost_api", "roost_mavlink"},
    "roost_agent": {"roost_api", "roost_kube", "roost_mavlink"},
    "roost_operator": {"roost_api", "roost_kube"},
    "roost_cli": {"roost_api", "roost_kube"},
    "roost_cli.sandbox": {
        "roost_api",
        "roost_kube",
        "roost_localcluster",
        "roost_mavlink",
        "roost_sim",
    },
    "roost_localcluster": {"roost_api", "roost_kube"},
}
NEVER_SHIPPED = {"tests", "bench"}
KOPF_USERS = {"roost_operator"}
CLIENT_AT_MODULE_LEVEL = {"roost_kube.client"}
# One Kubernetes layer: requests go through roost_kube.Kube everywhere. The CLI builds
# the ``kubernetes`` package's configuration itself (to word kubeconfig errors for a user)
# and hands it to Kube; no other module outside roost_kube touches the package.
KUBERNETES_PACKAGE_USERS = {"roost_cli.cluster"}
# Inside the operator: module prefix -> prefixes it never imports.
OPERATOR_NEVER: dict[str, set[str]] = {
    "roost_operator.autopilots": {"roost_operator.vehicles"},
}


def modules() -> list[tuple[str, Path]]:
    found = []
    for package, folder in PACKAGES.items():
        for path in sorted((REPO_ROOT / folder / package).rglob("*.py")):
            relative = path.relative_to(REPO_ROOT / folder).with_suffix("")
            found.append((".".join(relative.parts).removesuffix(".__init__"), path))
    return found


def imports(path: Path, *, module_level_only: bool = False) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = tree.body if module_level_only else list(ast.walk(tree))
    names: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def rule_for(module: str) -> str:
    return (
        "roost_cli.sandbox"
        if module.startswith("roost_cli.sandbox")
        else module.split(".", maxsplit=1)[0]
    )


MODULES = modules()


def test_every_package_is_checked() -> None:
    assert {rule_for(m) for m, _ in MODULES} == set(ALLOWED)


@pytest.mark.parametrize(("module", "path"), MODULES, ids=[m for m, _ in MODULES])
def test_imports_go_one_way(module: str, path: Path) -> None:
    own = module.split(".", maxsplit=1)[0]
    tops = {name.split(".")[0] for name in imports(path)}
    roost = {t for t in tops if t.startswith("roost_") and t != own}
    rule = rule_for(module)
    assert roost <= ALLOWED[rule], f"{module} imports {sorted(roost - ALLOWED[rule])}"
    assert not tops & NEVER_SHIPPED, f"{module} imports {sorted(tops & NEVER_SHIPPED)}"
    if own not in KOPF_USERS:
        assert "kopf" not in tops, f"{module} imports kopf"
    if own != "roost_kube" and module not in KUBERNETES_PACKAGE_USERS:
        assert "kubernetes" not in tops, f"{module} talks to the API server beside roost_kube"
    for prefix, never in OPERATOR_NEVER.items():
        if module == prefix or module.startswith(prefix + "."):
            bad = {n for n in imports(path) for p in never if n == p or n.startswith(p + ".")}
            assert not bad, f"{module} imports {sorted(bad)}"
    if own == "roost_kube" and module not in CLIENT_AT_MODULE_LEVEL:
        top_level = {n.split(".")[0] for n in imports(path, module_level_only=True)}
        assert "kubernetes" not in top_level, f"{module} imports the client at module level"
