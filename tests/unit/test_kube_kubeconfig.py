"""Kubeconfigs load as kubectl loads them, and every bad one is one line that says why.

The files are real files in a temp dir. The TLS check against a real HTTPS server and
``roost`` run as a program are in ``tests/integration/test_kube_kubeconfig_tls.py``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_cli.cluster import Fleet, resolve_kubeconfig
from roost_cli.errors import CliError
from roost_kube import kubeconfig
from roost_kube.kubeconfig import KubeconfigError


def config(server: str, name: str, *, current: bool = True) -> dict[str, Any]:
    body: dict[str, Any] = {
        "apiVersion": "v1",
        "kind": "Config",
        "clusters": [{"name": name, "cluster": {"server": server}}],
        "users": [{"name": name, "user": {"token": "t"}}],
        "contexts": [{"name": name, "context": {"cluster": name, "user": name}}],
    }
    if current:
        body["current-context"] = name
    return body


def write(path: Path, body: Any) -> Path:
    path.write_text(yaml.safe_dump(body))
    return path


def test_a_kubeconfig_list_is_merged_and_the_first_current_context_wins(tmp_path: Path) -> None:
    first = write(tmp_path / "a", config("http://127.0.0.1:1", "a"))
    second = write(tmp_path / "b", config("http://127.0.0.1:2", "b"))
    loaded = kubeconfig.load([first, second])
    assert loaded.host == "http://127.0.0.1:1"
    assert kubeconfig.load([first, second], context="b").host == "http://127.0.0.1:2"


def test_the_current_context_may_come_from_a_later_file(tmp_path: Path) -> None:
    first = write(tmp_path / "a", config("http://127.0.0.1:1", "a", current=False))
    second = write(tmp_path / "b", config("http://127.0.0.1:2", "b"))
    assert kubeconfig.load([first, second]).host == "http://127.0.0.1:2"


def test_missing_list_entries_are_skipped_as_kubectl_skips_them(tmp_path: Path) -> None:
    real = write(tmp_path / "real", config("http://127.0.0.1:3", "r"))
    environ = {"KUBECONFIG": os.pathsep.join([str(tmp_path / "gone"), str(real)])}
    target = resolve_kubeconfig(None, environ, None, tmp_path)
    assert (target.source, target.all_files) == ("$KUBECONFIG", (real,))


def test_an_unknown_context_lists_the_defined_ones(tmp_path: Path) -> None:
    path = write(tmp_path / "a", config("http://127.0.0.1:1", "a"))
    with pytest.raises(KubeconfigError, match=r"context 'nope' is not defined \(defined: a\)"):
        kubeconfig.load([path], context="nope")


def test_no_current_context_asks_for_one(tmp_path: Path) -> None:
    path = write(tmp_path / "a", config("http://127.0.0.1:1", "a", current=False))
    with pytest.raises(KubeconfigError, match="no current-context set; pass --context"):
        kubeconfig.load([path])


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("- a\n- b\n", "is not a kubeconfig: it is a list, not a mapping"),
        ("just text\n", "is not a kubeconfig: it is a str, not a mapping"),
        ("", "is not a kubeconfig: it is empty, not a mapping"),
        ("a: [\n", r"is not valid YAML \(line 2\)"),
    ],
)
def test_a_file_that_is_not_a_kubeconfig_mapping_says_so(
    tmp_path: Path, content: str, expected: str
) -> None:
    path = tmp_path / "bad"
    path.write_text(content)
    with pytest.raises(KubeconfigError, match=expected):
        kubeconfig.load([path])


def test_a_directory_is_reported_as_a_directory(tmp_path: Path) -> None:
    with pytest.raises(KubeconfigError, match="is a directory, not a kubeconfig file"):
        kubeconfig.load([tmp_path])


def test_a_binary_file_cannot_be_read(tmp_path: Path) -> None:
    path = tmp_path / "binary"
    path.write_bytes(b"\xff\xfe\x00config")
    with pytest.raises(KubeconfigError, match="cannot be read"):
        kubeconfig.load([path])


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_an_unreadable_file_says_permission_denied(tmp_path: Path) -> None:
    path = write(tmp_path / "locked", config("http://127.0.0.1:1", "a"))
    path.chmod(0)
    with pytest.raises(KubeconfigError, match="not readable"):
        kubeconfig.load([path])


def test_the_cli_turns_a_bad_kubeconfig_into_one_line(tmp_path: Path) -> None:
    path = tmp_path / "list"
    path.write_text("- not\n- a mapping\n")
    with pytest.raises(CliError) as error:
        Fleet(resolve_kubeconfig(path, {}, None, tmp_path))
    assert str(error.value) == (
        f"kubeconfig (--kubeconfig): {path} is not a kubeconfig: it is a list, not a mapping"
    )
    assert "\n" not in str(error.value)


def test_a_directory_given_as_kubeconfig_is_not_called_missing(tmp_path: Path) -> None:
    with pytest.raises(CliError, match="is a directory"):
        Fleet(resolve_kubeconfig(tmp_path, {}, None, tmp_path))
