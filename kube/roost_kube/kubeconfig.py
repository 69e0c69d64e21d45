"""Loading kubeconfigs exactly as kubectl does, with one-line errors a person can act on.

kubectl's rules, kept: ``--kubeconfig`` names one file; otherwise ``$KUBECONFIG`` is a
list of files (``:``-separated) merged in order — the first file to set a cluster, user,
context or ``current-context`` wins — where entries that do not exist are skipped;
otherwise ``~/.kube/config``. ``--context`` picks a context of the merged config instead
of its ``current-context``. The merge itself is the ``kubernetes`` client's loader (the
same code kubectl's rules were ported into), not ours, with one correction: the client's
merger lets the *last* file's ``current-context`` win, kubectl the first, so the context
is chosen here and passed to it.

What we add is the checking before it, so a bad file is reported as what it is instead
of a traceback from the YAML parser or a misleading "does not exist": a directory, an
unreadable file, a file that is not YAML, a file that is not a mapping, an unknown
context. Every problem is a :class:`KubeconfigError` whose text is the whole message.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

SEPARATOR = os.pathsep


class KubeconfigError(Exception):
    """A kubeconfig that cannot be used; ``str(error)`` is the whole one-line message."""


def split_list(value: str) -> list[Path]:
    """The files a ``$KUBECONFIG`` value names, in order, empty entries dropped."""
    return [Path(part).expanduser() for part in value.split(SEPARATOR) if part]


def read_file(path: Path) -> dict[str, Any]:
    """One kubeconfig file as a mapping, or a :class:`KubeconfigError` saying why not."""
    if path.is_dir():
        raise KubeconfigError(f"{path} is a directory, not a kubeconfig file")
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise KubeconfigError(f"{path} does not exist") from None
    except PermissionError:
        raise KubeconfigError(f"{path} is not readable (permission denied)") from None
    except (OSError, UnicodeDecodeError) as error:
        raise KubeconfigError(f"{path} cannot be read: {error}") from None
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError as error:
        where = getattr(error, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise KubeconfigError(f"{path} is not valid YAML{line}") from None
    if not isinstance(loaded, dict):
        found = "empty" if loaded is None else f"a {type(loaded).__name__}"
        raise KubeconfigError(f"{path} is not a kubeconfig: it is {found}, not a mapping")
    return loaded


def existing(files: Sequence[Path]) -> list[Path]:
    """The files of a list that exist (kubectl skips the others)."""
    return [path for path in files if path.exists()]


def check(files: Sequence[Path], context: str | None = None) -> str:
    """The context to use; :class:`KubeconfigError` unless the files merge into a usable one.

    Without ``context`` it is the first ``current-context`` of the list, as kubectl takes
    it (the client's merger would take the last one, so :func:`load` passes it on).
    """
    contexts: list[str] = []
    current = None
    for path in files:
        loaded = read_file(path)
        for entry in loaded.get("contexts") or []:
            if isinstance(entry, dict) and entry.get("name"):
                contexts.append(str(entry["name"]))
        current = current or loaded.get("current-context")
    wanted = context or current
    shown = ", ".join(str(path) for path in files)
    if not wanted:
        raise KubeconfigError(
            f"{shown}: no current-context set; pass --context (one of: "
            f"{', '.join(contexts) or 'none defined'})"
        )
    if wanted not in contexts:
        raise KubeconfigError(
            f"{shown}: context {wanted!r} is not defined (defined: {', '.join(contexts) or 'none'})"
        )
    return str(wanted)


def load(files: Sequence[Path], context: str | None = None) -> Any:
    """A ``kubernetes.client.Configuration`` for the merged ``files``.

    Raises :class:`KubeconfigError` for every problem :func:`check` finds and for what the
    client's loader refuses (a missing certificate file, an unsupported auth plugin).
    """
    from kubernetes import client, config  # noqa: PLC0415 - the client loads lazily

    chosen = check(files, context)
    configuration = client.Configuration()
    try:
        config.load_kube_config(  # type: ignore[no-untyped-call]
            config_file=SEPARATOR.join(str(path) for path in files),
            context=chosen,
            client_configuration=configuration,
            persist_config=False,
        )
    except (config.ConfigException, OSError, ValueError, TypeError) as error:
        shown = ", ".join(str(path) for path in files)
        detail = " ".join(str(error).split())
        raise KubeconfigError(f"{shown} cannot be used: {detail}") from None
    return configuration
