"""The test tree's layout, checked on the file names: unit tests mirror the packages.

A unit test file is named after the module it tests, ``test_<package>_<module>.py``:
the package without its ``roost_`` prefix, then the module's path inside it with ``_``
for ``/`` (``roost_operator/vehicles/plan.py`` → ``test_operator_vehicles_plan.py``).
A file may test a whole package (``test_api.py``), add an aspect after a module's name
(``test_agent_health_replay.py``: the health model against recorded flights), or check
the repository rather than a module (``test_repo_<what>.py``: import directions, image
files, kind-config.yaml, this layout). docs/contributing.md explains the tiers.

pytest imports test files by their base name, so no two files anywhere under tests/
may share one.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
REPO = TESTS.parent
SOURCE_ROOTS = ("api", "kube", "operator", "agent", "mavlink", "sim", "cli", "localcluster")


def package_and_module_keys() -> tuple[set[str], set[str]]:
    """``(packages, modules)``: every package and module of Roost as a file name spells it."""
    packages: set[str] = set()
    modules: set[str] = set()
    for root in SOURCE_ROOTS:
        for init in (REPO / root).glob("roost_*/**/__init__.py"):
            package = init.parent
            top = package.relative_to(REPO / root).parts
            prefix = "_".join((top[0].removeprefix("roost_"), *top[1:]))
            packages.add(prefix)
            modules.update(
                f"{prefix}_{source.stem}"
                for source in package.glob("*.py")
                if source.stem != "__init__"
            )
    return packages, modules


def subject(name: str, packages: set[str], modules: set[str]) -> str | None:
    """The package or module a unit test file's name says it tests, or None."""
    stem = name.removeprefix("test_").removesuffix(".py")
    if stem.startswith("repo_") or stem in packages or stem in modules:
        return stem
    prefixes = [m for m in modules if stem.startswith(m + "_")]
    return max(prefixes, key=len) if prefixes else None


def test_the_names_resolve_as_the_scheme_says() -> None:
    packages = {"operator", "operator_vehicles"}
    modules = {"operator_vehicles_plan", "agent_health", "agent_state", "agent_state_model"}
    assert subject("test_operator_vehicles_plan.py", packages, modules) == "operator_vehicles_plan"
    assert subject("test_operator_vehicles.py", packages, modules) == "operator_vehicles"
    assert subject("test_agent_health_replay.py", packages, modules) == "agent_health"
    assert subject("test_agent_state_model.py", packages, modules) == "agent_state_model"
    assert subject("test_repo_images.py", packages, modules) == "repo_images"
    assert subject("test_vehicle_plan.py", packages, modules) is None
    assert subject("test_operator_anything.py", packages, modules) is None  # not a module


def test_every_unit_test_file_names_a_module_of_roost() -> None:
    packages, modules = package_and_module_keys()
    assert "operator_vehicles_plan" in modules and "agent" in packages  # the walk finds them
    stray = [
        path.name
        for path in sorted((TESTS / "unit").glob("test_*.py"))
        if subject(path.name, packages, modules) is None
    ]
    assert not stray, (
        f"unit test files that name no module: {stray}; name them "
        "test_<package>_<module>.py (see docs/contributing.md)"
    )


def test_no_two_test_files_share_a_name() -> None:
    names = Counter(path.name for path in TESTS.rglob("test_*.py"))
    assert not [name for name, count in names.items() if count > 1]
