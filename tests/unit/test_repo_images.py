"""The image files, checked as text (tests/e2e/test_image_run.py builds and runs them).

The facts the chart and the build script rely on must hold: a target per
image whose entrypoint is one of the distribution's console scripts, a non-root user
equal to the chart's ``runAsUser``, a public base pinned to a release by default, and a
build context (written by ``docker/build-images.sh --context``) that carries everything
the Dockerfile copies. The real linters (``hadolint``, ``shellcheck``) run in
``tests/integration/test_images_lint.py``.
"""

from __future__ import annotations

import fnmatch
import json
import re
import tomllib

import pytest
import yaml

from roost_localcluster.binaries import REPO_ROOT

DOCKERFILE = REPO_ROOT / "docker" / "Dockerfile"
DOCKERIGNORE = REPO_ROOT / "docker" / "Dockerfile.dockerignore"
PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
VALUES = yaml.safe_load((REPO_ROOT / "charts" / "roost" / "values.yaml").read_text())
IMAGES = {"operator": "roost-operator", "agent": "roost-agent"}


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    joined = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    result = []
    for line in joined.splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            keyword, _, rest = stripped.partition(" ")
            result.append((keyword.upper(), rest.strip()))
    return result


def _stages() -> dict[str, list[tuple[str, str]]]:
    """Stage name -> its instructions, with the instructions of the stage it builds on."""
    stages: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] = []
    for keyword, rest in _instructions():
        if keyword == "FROM":
            base, _, name = rest.partition(" AS ")
            current = list(stages.get(base.strip(), []))
            stages[name.strip()] = current
        current.append((keyword, rest))
    return stages


@pytest.mark.parametrize("target", sorted(IMAGES))
def test_each_image_runs_its_console_script_as_the_charts_non_root_user(target: str) -> None:
    stage = _stages()[target]
    entrypoint = json.loads(next(rest for keyword, rest in stage if keyword == "ENTRYPOINT"))
    assert entrypoint == [IMAGES[target]]
    assert IMAGES[target] in PYPROJECT["project"]["scripts"]
    user = [rest for keyword, rest in stage if keyword == "USER"][-1]
    uid, _, gid = user.partition(":")
    chart_context = VALUES[target]["podSecurityContext"]
    assert int(uid) == chart_context["runAsUser"] != 0
    assert int(gid) == chart_context["runAsGroup"]


def test_default_base_is_pinned_to_a_release() -> None:
    args = dict(rest.partition("=")[::2] for keyword, rest in _instructions() if keyword == "ARG")
    base = args["BASE"]
    assert ":" in base and not base.endswith(":latest"), base
    froms = [rest.split()[0] for keyword, rest in _instructions() if keyword == "FROM"]
    assert all(image in {"${BASE}", "runtime"} for image in froms), froms


def test_build_context_carries_what_the_dockerfile_copies() -> None:
    """The context written by the build script, minus its wheels (built by pip on the
    real run), holds every COPY source, and the .dockerignore lets them through."""
    sources = {
        source
        for keyword, rest in _instructions()
        if keyword == "COPY" and "--from" not in rest
        for source in rest.split()[:-1]
    }
    script = (REPO_ROOT / "docker" / "build-images.sh").read_text()
    wheels = {source for source in sources if source.split("/")[0] == "wheels"}
    for source in sources - wheels:
        assert f'"$here/{source}"' in script, f"{source} is copied but not put in the context"
        assert (REPO_ROOT / "docker" / source).is_file()
    for source in wheels:  # the two directories of wheels the script writes
        assert f'"$ctx/{source}"' in script, f"{source} is copied but never written"
    patterns = [p for p in DOCKERIGNORE.read_text().splitlines() if p and p[0] != "#"]
    for source in sources:
        included = False
        top = source.split("/")[0]
        for pattern in patterns:
            if pattern.startswith("!"):
                included |= fnmatch.fnmatch(top, pattern[1:].rstrip("/"))
            elif fnmatch.fnmatch(source, pattern):
                included = False
        assert included, f"{source} is copied but excluded by {DOCKERIGNORE.name}"
