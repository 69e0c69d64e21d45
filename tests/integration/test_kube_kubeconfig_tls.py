"""Bad kubeconfigs through the real ``roost`` console script (one line, exit 1), and a TLS
failure told apart from a dead server against a real HTTPS server on 127.0.0.1 (Python's
own, serving one canned list: what is under test is the handshake and the message), with
certificates from :mod:`roost_localcluster.pki`. Loading rules are in ``tests/unit``.
"""

from __future__ import annotations

import http.server
import json
import os
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from roost_api.ports import free_port
from roost_cli.cluster import Fleet, Target
from roost_cli.errors import CliError
from roost_localcluster import pki


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

    dead = f"https://127.0.0.1:{free_port()}"  # nobody listens on it
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
