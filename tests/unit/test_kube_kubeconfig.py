"""Kubeconfigs load as kubectl loads them, and every bad one is one line that says why.

The files are real files in a temp dir; the TLS test talks to a real HTTPS server on
127.0.0.1 (Python's own, serving one canned list: what is under test is the TLS
handshake and the message, not the API server), with certificates from
:mod:`roost_localcluster.pki`.
"""

from __future__ import annotations

import http.server
import json
import os
import socket
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_cli.cluster import Fleet, Target, resolve_kubeconfig
from roost_cli.errors import CliError
from roost_kube import kubeconfig
from roost_kube.kubeconfig import KubeconfigError
from roost_localcluster import pki


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


@pytest.fixture
def https_server(tmp_path: Path) -> Iterator[tuple[str, pki.Pki]]:
    """An HTTPS server on 127.0.0.1 with a serving certificate of its own CA."""
    server_pki = pki.write_pki(tmp_path / "server-pki")

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = json.dumps({"kind": "VehicleList", "items": []}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_: Any) -> None:
            return

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(server_pki.serving_cert, server_pki.serving_key)
    httpd.socket = context.wrap_socket(httpd.socket, server_side=True)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"https://127.0.0.1:{httpd.server_address[1]}", server_pki
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join()


def test_a_certificate_failure_is_told_apart_from_a_dead_server(
    tmp_path: Path, https_server: tuple[str, pki.Pki]
) -> None:
    server, server_pki = https_server
    right = pki.write_kubeconfig(tmp_path / "right", server_pki, server, pki.ADMIN)
    assert Fleet(Target(right, "--kubeconfig")).vehicles() == []  # the control: TLS works

    other_pki = pki.write_pki(tmp_path / "other-pki")
    wrong = pki.write_kubeconfig(tmp_path / "wrong", other_pki, server, pki.ADMIN)
    with pytest.raises(CliError) as error:
        Fleet(Target(wrong, "--kubeconfig")).vehicles()
    message = str(error.value)
    assert message.startswith(f"TLS with the API server at {server} failed")
    assert "certificate verify failed" in message
    assert "Is the cluster running?" not in message and "\n" not in message

    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        dead = f"https://127.0.0.1:{probe.getsockname()[1]}"
    refused = pki.write_kubeconfig(tmp_path / "refused", server_pki, dead, pki.ADMIN)
    with pytest.raises(CliError, match="Is the cluster running"):
        Fleet(Target(refused, "--kubeconfig")).vehicles()


@pytest.mark.parametrize("kind", ["list", "directory", "merged"])
def test_roost_prints_one_line_and_exits_1(tmp_path: Path, kind: str) -> None:
    """The real ``roost`` command, in a narrow terminal: one line on stderr, no traceback."""
    bad = tmp_path / "bad"
    bad.write_text("- not\n- a mapping\n")
    args, env = [], {**os.environ, "COLUMNS": "40"}
    if kind == "list":
        args = ["--kubeconfig", str(bad)]
    elif kind == "directory":
        args = ["--kubeconfig", str(tmp_path)]
    else:
        env["KUBECONFIG"] = os.pathsep.join([str(tmp_path / "gone"), str(bad)])
    roost = Path(sys.executable).parent / "roost"
    result = subprocess.run(
        [str(roost), *args, "status"], capture_output=True, text=True, env=env, check=False
    )
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith("error: kubeconfig (")
