"""The image files and shell scripts through the real linters (``hadolint`` and
``shellcheck``, from their wheels, run as programs): they must report nothing.

The facts the chart and the build script rely on are checked as text in
``tests/unit/test_repo_images.py``; ``tests/e2e/test_image_run.py`` builds and runs them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from roost_localcluster.binaries import REPO_ROOT

DOCKERFILE = REPO_ROOT / "docker" / "Dockerfile"


def test_hadolint_reports_nothing() -> None:
    hadolint = Path(sys.executable).parent / "hadolint"
    result = subprocess.run(
        [str(hadolint), "--no-color", "--failure-threshold", "style", str(DOCKERFILE)],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert result.returncode == 0 and not result.stdout.strip(), result.stdout + result.stderr


SCRIPT_DIRS = ("docker", "localcluster", "tests/e2e/kind")


def test_shell_scripts_pass_shellcheck() -> None:
    """Every script the builds and CI run, checked from a directory that is not their own
    (a directive that only resolves from one working directory is a finding)."""
    shellcheck = Path(sys.executable).parent / "shellcheck"
    scripts = sorted(
        str(path) for folder in SCRIPT_DIRS for path in (REPO_ROOT / folder).rglob("*.sh")
    )
    scripts.append(str(REPO_ROOT / ".ci" / "run"))
    result = subprocess.run(
        [str(shellcheck), "--external-sources", *scripts],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
        cwd="/",
    )
    assert result.returncode == 0, result.stdout + result.stderr
